"""Loading and validating Prime's bundled, user-overridable configuration files."""

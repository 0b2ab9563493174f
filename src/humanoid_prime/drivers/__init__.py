"""The real hardware components, one package per bus or actuator family, with their pure protocol and maths."""

"""Benchmarks behind ``make bench``: each module measures one DESIGN §6 target and returns its figures."""

"""Helpers shared by the tests: small networks, instances and records made by hand.
Fixtures live in the conftest.py files."""

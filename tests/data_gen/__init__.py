"""Tests of the package data_gen, one file per module: tests/data_gen/test_<module>.py."""

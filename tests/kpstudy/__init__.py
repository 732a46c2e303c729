"""Tests of the package kpstudy, one file per module: tests/kpstudy/<package>/test_<module>.py
(tests/test_layout.py checks the mirror). This package is ``tests.kpstudy``: it is never
on ``sys.path`` itself, so it cannot stand in for the real ``kpstudy``."""

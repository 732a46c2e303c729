"""Tests of kpstudy.verify."""

"""Tests of kpstudy.study."""

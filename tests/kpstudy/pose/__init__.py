"""Tests of kpstudy.pose."""

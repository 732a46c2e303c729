"""Tests of kpstudy.models."""

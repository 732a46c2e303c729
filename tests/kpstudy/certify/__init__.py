"""Tests of kpstudy.certify."""

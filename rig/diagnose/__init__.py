"""Mismatch diagnosis (issue 7): locate where model and recording differ, name the missing physics, fit it."""

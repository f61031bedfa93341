"""Tracking simulated drives and drives over photographs of two dates."""

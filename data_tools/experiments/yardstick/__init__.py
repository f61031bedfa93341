"""Localization success against noise and scene change, per score: the yardstick and its data."""

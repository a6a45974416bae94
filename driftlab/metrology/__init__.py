"""Metrology in the machine-tool standards' terms: ISO 230-2 positioning, ISO 230-3 thermal tests, instrument
importers."""

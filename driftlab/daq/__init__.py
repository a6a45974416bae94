"""Instrument drivers: real transports and simulated ones behind the same interfaces."""

"""Streaming compensator: motion code in, corrected motion code out."""

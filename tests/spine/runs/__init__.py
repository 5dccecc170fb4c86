"""Whole runs: real processes end to end, what the terminal shows, picking, the window, the wire."""

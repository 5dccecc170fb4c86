"""The house itself: imports run one way, one error root, docs that match the code, stage kinds as records."""

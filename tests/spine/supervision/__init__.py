"""Supervision: restarts, hung or starved, orphans, the fork server, accounting under faults."""

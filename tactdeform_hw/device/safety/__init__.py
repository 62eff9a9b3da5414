"""Participant safety: the guard every current passes, the fail-safe watchdog, and the guardian processes
that switch a board off when its owner dies."""

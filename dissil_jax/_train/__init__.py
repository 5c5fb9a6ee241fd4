"""Trainers sharing one result type."""

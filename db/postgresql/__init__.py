"""Numbered SQL migrations of a line's central PostgreSQL results database."""

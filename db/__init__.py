"""Numbered SQL migrations of the station database, packaged so they ship with the code."""

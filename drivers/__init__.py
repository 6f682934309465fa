"""Hardware roles of the bench: one small abstraction per role, one module per transport."""

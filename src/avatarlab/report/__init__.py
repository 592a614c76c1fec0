"""Stage: the report - tables, claims, figures and the results card, read from the planned results only."""

"""Reading and writing recordings in the ETHZ format (docs/method.md 4)."""

"""Reading and writing recordings in the ETHZ format (design 4)."""

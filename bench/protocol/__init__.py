"""Protocol files: schema and validation, compilation into a timed program, dry-run prediction."""

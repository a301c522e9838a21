"""Analysis of recorded runs: figures of merit computed from files (and, in tests, from model traces)."""

"""``bench watch``: live plots of run files in a browser (server-side min/max decimation, pause and stop only)."""

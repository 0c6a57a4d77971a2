"""Studies of finished runs: sweeps, tables, reports, figures, timings."""

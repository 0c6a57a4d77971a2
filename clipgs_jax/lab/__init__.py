"""Studies of finished runs: sweeps, tables, reports, figures, timings,
the viewer; imports the library, never imported by it."""

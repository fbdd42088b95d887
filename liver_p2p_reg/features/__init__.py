"""Per-point feature providers (FPFH, learned) behind one small interface."""

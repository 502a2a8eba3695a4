"""Host-side optimisation loops of octcl (NumPy Adam, torch losses on the CPU)."""

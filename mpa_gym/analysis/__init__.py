"""Layer 2: the paper's analysis — stability (Theorem 1, Floquet), scenarios and simulation."""

"""Model: colour transforms and low-rank bases of measured BTFs (paper 1; paper 4 §3)."""

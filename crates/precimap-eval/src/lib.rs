//! Accuracy against simulated truth: strip offset spread, surface error, trajectory error.

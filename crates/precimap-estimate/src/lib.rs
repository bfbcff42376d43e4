//! Strip adjustment numerics: per-strip preparation, latent map, estimate_tile, solve_trajectory.

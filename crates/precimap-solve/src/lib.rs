//! Exact linear-time solver for the block-tridiagonal normal equations of one trajectory.

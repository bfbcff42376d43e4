//! Simulated mobile-mapping campaigns that know their truth.

pub mod truth;

//! Integration tests, linked as one binary: one link of the whole stack instead of one per file.

// First: its macros are visible to the modules declared after it.
#[macro_use]
mod common;

mod lifecycle;
mod store;

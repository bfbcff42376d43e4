//! Integration tests, linked as one binary: one link of the whole stack instead of one per file.

mod api;
mod common;
mod inputs;

//! Integration tests, linked as one binary: one link of the whole stack instead of one per file.

mod corpus;
mod field_files;
mod strip;

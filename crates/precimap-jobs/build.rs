//! `sqlx::migrate!` embeds the migrations at compile time but does not tell Cargo about them:
//! without this a new migration file would not rebuild the crate.
fn main() {
    println!("cargo:rerun-if-changed=../../migrations");
}

//! Embeds the SQL migrations (`migrations/{sqlite,postgres}/NNNN_description.sql`) into the crate
//! as `$OUT_DIR/migrations.rs`, one `(version, description, sql)` table per database. sqlx's
//! `migrate!` macro would do the same at the cost of its proc-macro crate, which compiles sqlx's
//! drivers a second time for the host.
use std::fmt::Write as _;
use std::path::Path;

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../migrations");
    println!("cargo:rerun-if-changed={}", root.display());
    let mut out = String::new();
    for (name, dir) in [("SQLITE", "sqlite"), ("POSTGRES", "postgres")] {
        let dir = root.join(dir);
        println!("cargo:rerun-if-changed={}", dir.display());
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("reading {}: {e}", dir.display()))
            .map(|entry| entry.expect("a directory entry").path())
            .filter(|path| path.extension().is_some_and(|ext| ext == "sql"))
            .collect();
        files.sort();
        writeln!(out, "pub(crate) const {name}: &[(i64, &str, &str)] = &[").unwrap();
        for path in files {
            let stem = path.file_stem().and_then(|s| s.to_str()).expect("a UTF-8 migration file name");
            let (version, description) =
                stem.split_once('_').unwrap_or_else(|| panic!("{}: expected NNNN_description.sql", path.display()));
            let version: i64 =
                version.parse().unwrap_or_else(|_| panic!("{}: version is not a number", path.display()));
            let description = description.replace('_', " ");
            let path = path.canonicalize().expect("a migration's path");
            writeln!(out, "    ({version}, {description:?}, include_str!({:?})),", path.display().to_string()).unwrap();
        }
        writeln!(out, "];").unwrap();
    }
    let out_dir = std::env::var("OUT_DIR").expect("OUT_DIR is set by Cargo");
    std::fs::write(Path::new(&out_dir).join("migrations.rs"), out).expect("writing migrations.rs");
}

//! The job store's schema migrations, embedded at build time (see `build.rs`) and run by sqlx's
//! migrator, which records each applied version with its checksum in `_sqlx_migrations`.

use std::borrow::Cow;

use futures::future::BoxFuture;
use sqlx::error::BoxDynError;
use sqlx::migrate::{Migration, MigrationSource, MigrationType, Migrator};

include!(concat!(env!("OUT_DIR"), "/migrations.rs"));

/// One database's migrations as `(version, description, sql)`, in version order.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Embedded(pub &'static [(i64, &'static str, &'static str)]);

impl MigrationSource<'static> for Embedded {
    fn resolve(self) -> BoxFuture<'static, Result<Vec<Migration>, BoxDynError>> {
        Box::pin(async move { Ok(self.migrations()) })
    }
}

impl Embedded {
    /// As sqlx reads a migrations folder: a file is a simple (up-only) migration, run in a
    /// transaction unless it starts with `-- no-transaction`; the checksum is the SQL's SHA-384.
    fn migrations(self) -> Vec<Migration> {
        self.0
            .iter()
            .map(|&(version, description, sql)| {
                let no_tx = sql.starts_with("-- no-transaction");
                Migration::new(version, Cow::Borrowed(description), MigrationType::Simple, Cow::Borrowed(sql), no_tx)
            })
            .collect()
    }

    pub(crate) async fn migrator(self) -> Result<Migrator, sqlx::migrate::MigrateError> {
        Migrator::new(self).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The embedded tables are the folders' files, so a database migrated by an earlier build
    /// (which recorded each file's checksum) still validates.
    #[tokio::test]
    async fn embedded_migrations_match_the_folders() {
        for (embedded, folder) in [(Embedded(SQLITE), "sqlite"), (Embedded(POSTGRES), "postgres")] {
            let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../migrations").join(folder);
            let from_folder = Migrator::new(dir).await.expect("the migrations folder resolves");
            let embedded = embedded.migrator().await.expect("the embedded migrations resolve");
            let key = |m: &Migration| (m.version, m.description.to_string(), m.checksum.to_vec(), m.no_tx);
            let a: Vec<_> = from_folder.iter().map(key).collect();
            let b: Vec<_> = embedded.iter().map(key).collect();
            assert!(!a.is_empty(), "{folder}: no migrations found");
            assert_eq!(a, b, "{folder}");
        }
    }
}

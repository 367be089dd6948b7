//! Which database holds the rows: an SQLite file (the embedded default: one command, one
//! machine) or a PostgreSQL server (several API replicas and workers on one database, issue 17).
//! One code path serves both — sqlx's `Any` driver, `$N` placeholders (SQLite reads them as
//! its numbered parameters), portable SQL — and a migration folder per dialect.

use std::fmt;
use std::path::{Path, PathBuf};

use sqlx::{Any, Transaction};

use super::DB_FILE;
use super::error::{Result, StoreError};

/// The database engine.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Sqlite,
    Postgres,
}

/// Where the database lives, from a URL: `sqlite://PATH` (or `sqlite:PATH`) or
/// `postgres://USER:PASSWORD@HOST:PORT/DB?…` (`postgresql://` too). `Debug` and `Display` never
/// show a password.
#[derive(Clone, PartialEq, Eq)]
pub enum Database {
    /// An SQLite file (created when missing).
    Sqlite(PathBuf),
    /// A PostgreSQL connection URL (the database must exist).
    Postgres(String),
}

impl Database {
    /// The default: `data_dir/splatmark.db`.
    pub fn in_data_dir(data_dir: &Path) -> Self {
        Database::Sqlite(data_dir.join(DB_FILE))
    }

    /// Parses a database URL (`Invalid` for any other scheme, or an SQLite URL without a path).
    pub fn parse(url: &str) -> Result<Self> {
        let url = url.trim();
        if let Some(rest) = url
            .strip_prefix("sqlite://")
            .or_else(|| url.strip_prefix("sqlite:"))
        {
            let path = rest.split('?').next().unwrap_or_default();
            if path.is_empty() {
                return Err(StoreError::invalid("an sqlite:// URL needs a file path"));
            }
            return Ok(Database::Sqlite(PathBuf::from(path)));
        }
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            return Ok(Database::Postgres(url.to_owned()));
        }
        Err(StoreError::invalid(format!(
            "database URL must start with sqlite:// or postgres:// (got {})",
            redact(url)
        )))
    }

    pub fn backend(&self) -> Backend {
        match self {
            Database::Sqlite(_) => Backend::Sqlite,
            Database::Postgres(_) => Backend::Postgres,
        }
    }

    /// The URL itself, as sqlx connects with it (may hold a password: never log it; `Display`
    /// hides it).
    pub fn url(&self) -> String {
        match self {
            Database::Sqlite(path) => format!("sqlite://{}", percent_encode_path(path)),
            Database::Postgres(url) => url.clone(),
        }
    }
}

impl std::str::FromStr for Database {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Database::parse(s).map_err(|e| e.to_string())
    }
}

/// Read from a config file as its URL; written back with any password replaced by `***`
/// (a configuration dump never carries it).
impl<'de> serde::Deserialize<'de> for Database {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let url = String::deserialize(d)?;
        Database::parse(&url).map_err(serde::de::Error::custom)
    }
}

impl serde::Serialize for Database {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_string())
    }
}

impl fmt::Display for Database {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Database::Sqlite(path) => write!(f, "sqlite://{}", path.display()),
            Database::Postgres(url) => f.write_str(&redact(url)),
        }
    }
}

impl fmt::Debug for Database {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Database({self})")
    }
}

/// `url` with the password of its user-info (`user:password@`) and any `password=` query
/// parameter replaced by `***`.
pub fn redact(url: &str) -> String {
    let mut out = url.to_owned();
    if let Some(scheme_end) = out.find("://") {
        let auth_start = scheme_end + 3;
        let auth_end = out[auth_start..]
            .find(['/', '?', '#'])
            .map_or(out.len(), |i| auth_start + i);
        if let Some(at) = out[auth_start..auth_end].rfind('@') {
            let userinfo = &out[auth_start..auth_start + at];
            if let Some(colon) = userinfo.find(':') {
                out.replace_range(auth_start + colon + 1..auth_start + at, "***");
            }
        }
    }
    if let Some(q) = out.find('?') {
        let (head, query) = out.split_at(q + 1);
        let query = query
            .split('&')
            .map(|kv| match kv.split_once('=') {
                Some((k, _)) if k.eq_ignore_ascii_case("password") => format!("{k}=***"),
                _ => kv.to_owned(),
            })
            .collect::<Vec<_>>()
            .join("&");
        out = format!("{head}{query}");
    }
    out
}

/// A path as the path part of an `sqlite://` URL (sqlx percent-decodes it).
fn percent_encode_path(path: &Path) -> String {
    let mut out = String::new();
    for b in path.to_string_lossy().bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'/' | b'-' | b'_' | b'.' | b'~') {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

/// Creates the new, empty database `name` (letters, digits, `_`) on the PostgreSQL server
/// `server` (a URL without a database path) and returns it — the tests' fresh databases.
pub async fn create_postgres(server: &str, name: &str) -> Result<Database> {
    use sqlx::Connection;
    if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Err(StoreError::invalid(format!("database name {name:?}")));
    }
    let server = server.trim_end_matches('/');
    sqlx::any::install_default_drivers();
    let mut admin = sqlx::AnyConnection::connect(&format!("{server}/postgres")).await?;
    sqlx::query(sqlx::AssertSqlSafe(format!("CREATE DATABASE {name}")))
        .execute(&mut admin)
        .await?;
    admin.close().await?;
    Ok(Database::Postgres(format!("{server}/{name}")))
}

/// The key of the PostgreSQL advisory lock every write transaction takes first
/// ([`write_lock`]): ASCII "splatmrk".
pub(crate) const WRITE_LOCK: i64 = 0x7370_6c61_746d_726b;

/// Takes the write lock in `tx` (PostgreSQL; released at commit or rollback). Writers of all
/// processes on the database queue here, in the order they asked, as SQLite's writers queue on
/// its file lock; readers never wait for it.
pub(crate) async fn write_lock(tx: &mut Transaction<'static, Any>) -> Result<()> {
    // The function returns `void`, which sqlx's `Any` rows cannot carry: select a constant.
    sqlx::query("SELECT 1 FROM pg_advisory_xact_lock($1)")
        .bind(WRITE_LOCK)
        .execute(&mut **tx)
        .await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_parse_to_their_backend() {
        assert_eq!(
            Database::parse("sqlite:///var/lib/splatmark/s.db").unwrap(),
            Database::Sqlite("/var/lib/splatmark/s.db".into())
        );
        assert_eq!(
            Database::parse("sqlite:data/s.db?mode=rwc").unwrap(),
            Database::Sqlite("data/s.db".into())
        );
        let pg = Database::parse("postgresql://u:p@db:5432/splatmark").unwrap();
        assert_eq!(pg.backend(), Backend::Postgres);
        assert!(Database::parse("mysql://u@h/db").is_err());
        assert!(Database::parse("sqlite://").is_err());
    }

    #[test]
    fn a_password_never_prints() {
        let db =
            Database::parse("postgres://app:s3cr3t@db.internal:5432/sm?sslmode=require").unwrap();
        for shown in [format!("{db}"), format!("{db:?}")] {
            assert!(!shown.contains("s3cr3t"), "{shown}");
            assert!(shown.contains("app:***@db.internal:5432/sm"), "{shown}");
        }
        let q = redact("postgres://db/sm?user=app&password=s3cr3t&sslmode=disable");
        assert_eq!(q, "postgres://db/sm?user=app&password=***&sslmode=disable");
        let err = Database::parse("mysql://app:s3cr3t@h/db")
            .unwrap_err()
            .to_string();
        assert!(!err.contains("s3cr3t"), "{err}");
    }

    #[test]
    fn sqlite_paths_survive_the_url() {
        let db = Database::Sqlite("/tmp/a dir/with?#%/s.db".into());
        let url = db.url();
        assert!(!url[9..].contains(['?', '#', ' ']), "{url}");
        let back: sqlx::sqlite::SqliteConnectOptions = url.parse().unwrap();
        assert_eq!(back.get_filename(), Path::new("/tmp/a dir/with?#%/s.db"));
    }
}

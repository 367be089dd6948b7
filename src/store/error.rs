//! The storage layer's error type.

/// Everything the storage layer can fail with. Messages never contain keys or messages.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The row or blob asked for does not exist.
    #[error("not found")]
    NotFound,
    /// The request contradicts what is stored (idempotency key reused with another body, job
    /// already finished, result already published, ...).
    #[error("conflict: {0}")]
    Conflict(String),
    /// The lease token no longer holds the job (expired and re-claimed, cancelled or finished).
    #[error("lease lost")]
    LeaseLost,
    /// Authenticated decryption failed: wrong master key or tampered ciphertext.
    #[error("decryption failed (wrong master key or tampered data)")]
    Crypto,
    /// A file-system error.
    #[error("i/o: {0}")]
    Io(#[from] std::io::Error),
    /// A database error.
    #[error("database: {0}")]
    Db(#[from] sqlx::Error),
    /// Applying the schema migrations failed.
    #[error("migration: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    /// Bad input (nothing was written).
    #[error("invalid: {0}")]
    Invalid(String),
    /// A stored blob's bytes are not the ones its name (their SHA-256) and size promise: a
    /// corrupted or overwritten object in the blob store. Nothing was cached or returned.
    #[error("blob integrity: {0}")]
    BlobCorrupt(String),
}

impl StoreError {
    /// Shorthand for [`StoreError::Invalid`].
    pub(crate) fn invalid(msg: impl Into<String>) -> Self {
        StoreError::Invalid(msg.into())
    }

    /// A stored value that does not decode (a corrupt or hand-edited database).
    pub(crate) fn corrupt(msg: impl Into<String>) -> Self {
        StoreError::Db(sqlx::Error::Decode(msg.into().into()))
    }

    /// Maps constraint violations that input can cause to typed errors; others stay `Db`.
    pub(crate) fn from_db(e: sqlx::Error) -> Self {
        if let sqlx::Error::Database(d) = &e {
            if d.is_unique_violation() {
                return StoreError::Conflict(d.message().to_owned());
            }
            if d.is_foreign_key_violation() {
                return StoreError::Invalid("a referenced row does not exist".into());
            }
        }
        StoreError::Db(e)
    }
}

/// `Result` with [`StoreError`].
pub type Result<T, E = StoreError> = std::result::Result<T, E>;

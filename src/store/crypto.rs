//! The master key and the AEAD (XChaCha20-Poly1305) that keeps watermark messages encrypted at
//! rest. The plaintext of a message is its bit string as ASCII `0`/`1`; the associated data binds
//! each ciphertext to the row it belongs to, so a ciphertext copied onto another row fails.

use super::error::{Result, StoreError};
use chacha20poly1305::aead::{Aead, KeyInit, Payload};
use chacha20poly1305::{XChaCha20Poly1305, XNonce};
use std::fmt;
use std::io::Write;
use std::path::Path;
use zeroize::Zeroizing;

/// Environment variable holding the master key as 64 hex digits (takes precedence over the file).
pub const MASTER_KEY_ENV: &str = "SPLATMARK_MASTER_KEY";

const NONCE_LEN: usize = 24;

/// The 32-byte key that encrypts every stored message. Zeroed on drop; never printed.
#[derive(Clone)]
pub struct MasterKey(Zeroizing<[u8; 32]>);

impl fmt::Debug for MasterKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("MasterKey(***)")
    }
}

impl MasterKey {
    /// Parses 64 hex digits (surrounding whitespace ignored).
    pub fn from_hex(s: &str) -> Result<Self> {
        let s = s.trim();
        let mut key = Zeroizing::new([0u8; 32]);
        hex::decode_to_slice(s, &mut key[..])
            .map_err(|_| StoreError::invalid("master key must be 64 hex digits"))?;
        Ok(MasterKey(key))
    }

    /// A fresh key from the operating system's random source.
    pub fn generate() -> Self {
        let mut key = Zeroizing::new([0u8; 32]);
        fill_random(&mut key[..]);
        MasterKey(key)
    }

    /// The key as 64 lowercase hex digits (for writing the key file; never log it).
    pub fn to_hex(&self) -> String {
        hex::encode(&self.0[..])
    }

    /// The key from `SPLATMARK_MASTER_KEY` when set, else from `file` (64 hex digits), else a new
    /// key written to `file` with mode 0600 (temp file + fsync + no-clobber rename, so two
    /// processes starting at once end up with the same key).
    pub fn load_or_create(file: &Path) -> Result<Self> {
        if let Ok(hex) = std::env::var(MASTER_KEY_ENV) {
            return Self::from_hex(&hex);
        }
        Self::load_or_create_file(file)
    }

    /// The key in `file`, else a new key written there as [`Self::load_or_create`] does — never
    /// the environment's (a rotation's new key must be new even where `SPLATMARK_MASTER_KEY`
    /// holds the current one).
    pub fn load_or_create_file(file: &Path) -> Result<Self> {
        match std::fs::read_to_string(file) {
            Ok(text) => {
                warn_if_readable_by_others(file);
                return Self::from_hex(&Zeroizing::new(text));
            }
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e.into()),
            Err(_) => {}
        }
        let dir = match file.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        std::fs::create_dir_all(dir)?;
        let key = Self::generate();
        // tempfile creates the file with mode 0600 on Unix.
        let mut tmp = tempfile::NamedTempFile::new_in(dir)?;
        tmp.write_all(Zeroizing::new(key.to_hex()).as_bytes())?;
        tmp.write_all(b"\n")?;
        tmp.as_file().sync_all()?;
        match tmp.persist_noclobber(file) {
            Ok(_) => {
                super::blobs::sync_dir(dir)?;
                tracing::info!(path = %file.display(), "created a new master key file");
                Ok(key)
            }
            Err(e) if e.error.kind() == std::io::ErrorKind::AlreadyExists => {
                Self::from_hex(&Zeroizing::new(std::fs::read_to_string(file)?))
            }
            Err(e) => Err(e.error.into()),
        }
    }
}

/// Logs a warning (the path only) when the key file is readable by group or others.
fn warn_if_readable_by_others(file: &Path) {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        if let Ok(m) = std::fs::metadata(file)
            && m.permissions().mode() & 0o077 != 0
        {
            tracing::warn!(path = %file.display(), "master key file is readable by group or others; chmod 600 it");
        }
    }
    #[cfg(not(unix))]
    let _ = file;
}

/// Fills `buf` from the OS random source. Failing to get randomness is not recoverable.
pub(crate) fn fill_random(buf: &mut [u8]) {
    if let Err(e) = getrandom::fill(buf) {
        panic!("the operating system's random source failed: {e}");
    }
}

/// A sealed value: random nonce and ciphertext with its tag.
pub(crate) struct Sealed {
    pub nonce: Vec<u8>,
    pub ciphertext: Vec<u8>,
}

/// The AEAD under the master key.
#[derive(Clone)]
pub(crate) struct Cipher(XChaCha20Poly1305);

impl Cipher {
    pub fn new(key: &MasterKey) -> Self {
        Cipher(XChaCha20Poly1305::new(&(*key.0).into()))
    }

    pub fn seal(&self, plaintext: &[u8], aad: &[u8]) -> Result<Sealed> {
        let mut nonce = [0u8; NONCE_LEN];
        fill_random(&mut nonce);
        let ciphertext = self
            .0
            .encrypt(
                &XNonce::from(nonce),
                Payload {
                    msg: plaintext,
                    aad,
                },
            )
            .map_err(|_| StoreError::Crypto)?;
        Ok(Sealed {
            nonce: nonce.to_vec(),
            ciphertext,
        })
    }

    pub fn open(&self, nonce: &[u8], ciphertext: &[u8], aad: &[u8]) -> Result<Zeroizing<Vec<u8>>> {
        let nonce: [u8; NONCE_LEN] = nonce.try_into().map_err(|_| StoreError::Crypto)?;
        self.0
            .decrypt(
                &XNonce::from(nonce),
                Payload {
                    msg: ciphertext,
                    aad,
                },
            )
            .map(Zeroizing::new)
            .map_err(|_| StoreError::Crypto)
    }

    /// Seals a message (bit string) bound to `aad`.
    pub fn seal_bits(&self, bits: &[bool], aad: &[u8]) -> Result<Sealed> {
        let text = Zeroizing::new(bits_to_ascii(bits));
        self.seal(&text, aad)
    }

    /// Opens a message sealed by [`Cipher::seal_bits`].
    pub fn open_bits(&self, nonce: &[u8], ciphertext: &[u8], aad: &[u8]) -> Result<Vec<bool>> {
        let text = self.open(nonce, ciphertext, aad)?;
        text.iter()
            .map(|&c| match c {
                b'0' => Ok(false),
                b'1' => Ok(true),
                _ => Err(StoreError::Crypto),
            })
            .collect()
    }
}

/// The bit string as ASCII `0`/`1`.
pub(crate) fn bits_to_ascii(bits: &[bool]) -> Vec<u8> {
    bits.iter().map(|&b| if b { b'1' } else { b'0' }).collect()
}

/// The constant sealed into `meta` at creation so that a wrong master key is refused at open.
pub(crate) const KEY_CHECK_PLAINTEXT: &[u8] = b"splatmark master key check v1";
/// Associated data of that check value.
pub(crate) const KEY_CHECK_AAD: &[u8] = b"splatmark/meta/key_check";

//! The local read cache's pruning: the age rule, then the size bound (least recently used
//! first, sparing copies used within [`CACHE_GRACE`]).

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::CACHE_GRACE;
use crate::store::blobs::modified_longer_ago;

/// Prunes the cache folder `dir` (`ab/cdef…` files): removes the files not modified for
/// `max_age`, then — when `max_bytes` > 0 and the rest exceeds it — the least recently
/// modified ones down to 90 % of `max_bytes`, sparing those modified within [`CACHE_GRACE`].
/// Returns the bytes left.
pub(super) fn prune(dir: &Path, max_age: Duration, max_bytes: u64) -> u64 {
    let mut kept: Vec<(std::time::SystemTime, u64, PathBuf)> = Vec::new();
    let Ok(heads) = fs::read_dir(dir) else {
        return 0;
    };
    for head in heads.flatten() {
        let Ok(files) = fs::read_dir(head.path()) else {
            continue;
        };
        for f in files.flatten() {
            if modified_longer_ago(&f, max_age) {
                let _ = fs::remove_file(f.path());
                continue;
            }
            if let Ok(m) = f.metadata()
                && m.is_file()
            {
                let when = m.modified().unwrap_or(std::time::SystemTime::UNIX_EPOCH);
                kept.push((when, m.len(), f.path()));
            }
        }
    }
    let mut total: u64 = kept.iter().map(|k| k.1).sum();
    if max_bytes == 0 || total <= max_bytes {
        return total;
    }
    let target = max_bytes / 10 * 9;
    kept.sort();
    for (when, size, path) in kept {
        if total <= target {
            break;
        }
        let recent = when.elapsed().map_or(true, |age| age < CACHE_GRACE);
        if !recent && fs::remove_file(&path).is_ok() {
            total -= size;
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::fs::File;

    #[test]
    fn the_cache_keeps_the_recently_used_copies_within_its_bound() {
        let dir = tempfile::tempdir().expect("tmp");
        let now = std::time::SystemTime::now();
        let hours = |h: u64| now - Duration::from_secs(h * 3600);
        // name, bytes, last used
        let files = [
            ("aa/old", 100, hours(30)),
            ("ab/lru", 400, hours(5)),
            ("ac/mid", 300, hours(3)),
            ("ad/new", 200, hours(1)),
            ("ae/now", 500, now),
        ];
        for (name, size, when) in files {
            let p = dir.path().join(name);
            fs::create_dir_all(p.parent().unwrap()).unwrap();
            fs::write(&p, vec![7u8; size]).unwrap();
            File::options()
                .write(true)
                .open(&p)
                .unwrap()
                .set_modified(when)
                .unwrap();
        }
        let day = Duration::from_secs(24 * 3600);
        let exists = |n: &str| dir.path().join(n).exists();
        // Unbounded: only the age rule.
        assert_eq!(prune(dir.path(), day, 0), 1400);
        assert!(!exists("aa/old"));
        // Within the bound: nothing goes.
        assert_eq!(prune(dir.path(), day, 1400), 1400);
        // Past it: the least recently used go until ≤ 90 % of the bound (1 000 → 900).
        assert_eq!(prune(dir.path(), day, 1000), 700);
        assert!(!exists("ab/lru") && !exists("ac/mid"));
        assert!(exists("ad/new") && exists("ae/now"));
        // A copy used within the grace period stays even past the bound.
        assert_eq!(prune(dir.path(), day, 100), 500);
        assert!(exists("ae/now") && !exists("ad/new"));
    }
}

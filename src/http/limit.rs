//! Rate limits: a token bucket per key (an API key's id, a client address). `/v1/verify` is
//! limited per API key (`verify_per_minute`), failed authentication per client address
//! (`auth_failures_per_minute`); an empty bucket is a 429 with `Retry-After`.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::Instant;

/// Buckets kept before the full ones (idle keys) are dropped.
const MAX_KEYS: usize = 10_000;

/// Token buckets of `per_minute` tokens each, refilled continuously.
pub struct RateLimiter {
    capacity: f64,
    per_second: f64,
    buckets: Mutex<HashMap<String, (f64, Instant)>>,
}

impl RateLimiter {
    /// `per_minute` ≥ 1 requests a minute, in bursts of up to `per_minute`.
    pub fn per_minute(per_minute: u32) -> Self {
        let capacity = f64::from(per_minute.max(1));
        Self {
            capacity,
            per_second: capacity / 60.0,
            buckets: Mutex::new(HashMap::new()),
        }
    }

    /// Takes a token of `key`'s bucket; `Err(seconds)` (≥ 1) until one is there again.
    pub fn take(&self, key: &str) -> Result<(), u32> {
        self.take_at(key, Instant::now())
    }

    /// Whether `key`'s bucket is empty now, without taking from it.
    pub fn exhausted(&self, key: &str) -> Option<u32> {
        let now = Instant::now();
        let b = self.buckets.lock().unwrap_or_else(|e| e.into_inner());
        let (tokens, at) = b.get(key).copied()?;
        let tokens = self.refill(tokens, at, now);
        (tokens < 1.0).then(|| self.wait(tokens))
    }

    fn refill(&self, tokens: f64, at: Instant, now: Instant) -> f64 {
        (tokens + now.duration_since(at).as_secs_f64() * self.per_second).min(self.capacity)
    }

    fn wait(&self, tokens: f64) -> u32 {
        (((1.0 - tokens) / self.per_second).ceil() as u32).max(1)
    }

    fn take_at(&self, key: &str, now: Instant) -> Result<(), u32> {
        let mut b = self.buckets.lock().unwrap_or_else(|e| e.into_inner());
        if b.len() >= MAX_KEYS && !b.contains_key(key) {
            b.retain(|_, (t, at)| self.refill(*t, *at, now) < self.capacity);
        }
        let entry = b.entry(key.to_string()).or_insert((self.capacity, now));
        let tokens = self.refill(entry.0, entry.1, now);
        if tokens >= 1.0 {
            *entry = (tokens - 1.0, now);
            Ok(())
        } else {
            *entry = (tokens, now);
            Err(self.wait(tokens))
        }
    }
}

/// The service's limits.
pub struct Limits {
    /// Per API key id, on `/v1/verify`.
    pub verify: RateLimiter,
    /// Per client address, on requests whose API key is missing, malformed, unknown or revoked.
    pub auth_failures: RateLimiter,
}

impl Limits {
    pub fn new(verify_per_minute: u32, auth_failures_per_minute: u32) -> Self {
        Self {
            verify: RateLimiter::per_minute(verify_per_minute),
            auth_failures: RateLimiter::per_minute(auth_failures_per_minute),
        }
    }
}

/// The client's address as the connection loop recorded it (`http::server`); requests built
/// without one (unit tests of the router) share one bucket.
pub fn client_key(ip: Option<IpAddr>) -> String {
    ip.map_or_else(|| "unknown".to_string(), |ip| ip.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_bucket_allows_its_burst_then_refills_at_its_rate() {
        let l = RateLimiter::per_minute(3);
        let t0 = Instant::now();
        for _ in 0..3 {
            assert_eq!(l.take_at("k", t0), Ok(()));
        }
        // Empty: one token comes back every 20 s.
        assert_eq!(l.take_at("k", t0), Err(20));
        assert_eq!(l.take_at("k", t0 + Duration::from_secs(10)), Err(10));
        assert_eq!(l.take_at("k", t0 + Duration::from_secs(21)), Ok(()));
        // Other keys have their own bucket.
        assert_eq!(l.take_at("other", t0), Ok(()));
        // A full minute later the burst is back, no more.
        let later = t0 + Duration::from_secs(600);
        for _ in 0..3 {
            assert_eq!(l.take_at("k", later), Ok(()));
        }
        assert!(l.take_at("k", later).is_err());
    }

    #[test]
    fn idle_keys_are_forgotten_when_the_table_is_full() {
        let l = RateLimiter::per_minute(1);
        let t0 = Instant::now();
        for i in 0..MAX_KEYS {
            let _ = l.take_at(&i.to_string(), t0);
        }
        // A minute later every bucket is full again: the next new key clears them.
        let _ = l.take_at("new", t0 + Duration::from_secs(61));
        assert_eq!(l.buckets.lock().unwrap().len(), 1);
    }
}

//! The process's allocator settings.
//!
//! Rendering, decoding and back-propagating at 512² or more allocates and frees buffers of
//! megabytes to hundreds of megabytes at every step. glibc's malloc serves blocks above its
//! (dynamic) mmap threshold with fresh `mmap`s and hands them back with `munmap` on free, so
//! each step paid page faults, page zeroing and TLB shootdowns for memory it had just released:
//! a third of the CPU time of an embedding's calibration went to the kernel (perf, donut at
//! 512²). [`tune`] keeps blocks up to 1 GiB in the heap and lets it keep up to 512 MiB of free
//! memory at its top; docs/BENCHMARKS.md has the measured effect.

/// Largest block served from the heap instead of a private mapping.
pub const MMAP_THRESHOLD: usize = 1 << 30;
/// Free memory at the top of the heap kept for reuse instead of returned to the system.
pub const TRIM_THRESHOLD: usize = 512 << 20;

/// Applies the settings above to glibc's malloc; returns whether it took them (elsewhere — musl,
/// other systems — it does nothing and returns false).
pub fn tune() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt only changes malloc's parameters; it is called before any thread starts.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD as libc::c_int) == 1
                && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD as libc::c_int) == 1
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn glibc_takes_the_settings() {
        assert!(super::tune(), "mallopt refused the thresholds");
    }
}

//! Keep the memory a forward pass frees, instead of handing it back to the kernel and faulting
//! it in again, zeroed, on the next frame.
//!
//! A CPU forward pass allocates and frees tensors of 1–30 MB (a ViT-S at 518×686: the DPT
//! head's feature maps, the attention's score blocks). glibc's `malloc` serves the larger ones
//! with `mmap` until its dynamic threshold has grown past them, and gives the top of the heap
//! back (`M_TRIM_THRESHOLD`, 128 kB) whenever that much is free. Every frame then pays a page
//! fault and a page clear per 4 kB (or 2 MB with transparent huge pages) of its tensors:
//! `clear_page_erms` was 8.9 % of the samples of an int8 ViT-S run (`perf record` of
//! `bench_candle --dtype int8`), and 0 % with the settings below, with the same peak RSS
//! (241 → 247 MiB): the memory is used again on the next frame anyway.
//!
//! The settings are the process's (`mallopt`), made once, when the first CPU model is built:
//! blocks up to 32 MiB (glibc's largest allowed threshold on 64-bit) come from the heap, and the
//! heap keeps up to 1 GiB of free memory at its top. Nothing is done when the user set any
//! `glibc.malloc.*` tunable in `GLIBC_TUNABLES` (their choice wins), nor outside glibc.

/// Largest `M_MMAP_THRESHOLD` glibc accepts on 64-bit targets (`HEAP_MAX_SIZE / 2`), bytes.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD_BYTES: libc::c_int = 32 << 20;

/// Free memory the heap keeps at its top before giving it back, bytes.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const TRIM_THRESHOLD_BYTES: libc::c_int = 1 << 30;

/// Applies the settings of this module once per process (see there). Returns whether they are
/// in effect (`false`: not glibc, the user's `GLIBC_TUNABLES` decide, or `mallopt` refused).
pub(crate) fn keep_freed_memory() -> bool {
    static APPLIED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *APPLIED.get_or_init(apply)
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn apply() -> bool {
    let user_tuned = std::env::var("GLIBC_TUNABLES").is_ok_and(|t| t.contains("glibc.malloc."));
    if user_tuned {
        return false;
    }
    // SAFETY: mallopt only changes allocator parameters; it is thread-safe (it takes the arena
    // locks) and returns 0 when it rejects a value.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
            && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn apply() -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn glibc_accepts_the_settings_unless_the_user_tuned_malloc() {
        let user_tuned = std::env::var("GLIBC_TUNABLES").is_ok_and(|t| t.contains("glibc.malloc."));
        // once applied, a second call changes nothing and says the same
        assert_eq!(keep_freed_memory(), !user_tuned);
        assert_eq!(keep_freed_memory(), !user_tuned);
    }
}

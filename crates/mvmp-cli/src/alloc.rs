//! The binary's global allocator: mimalloc with a count of the bytes live and their peak, which
//! `mvmp bench attention` reads (the peak can be reset between measurements, which allocator-stats crates
//! such as `cap` do not offer).
use std::alloc::{GlobalAlloc, Layout};
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

pub struct Counting<A> {
    inner: A,
    live: AtomicUsize,
    peak: AtomicUsize,
}

impl<A> Counting<A> {
    pub const fn new(inner: A) -> Self {
        Counting {
            inner,
            live: AtomicUsize::new(0),
            peak: AtomicUsize::new(0),
        }
    }

    /// Start a new peak at the bytes live now, which it returns.
    pub fn reset_peak(&self) -> usize {
        let now = self.live.load(Relaxed);
        self.peak.store(now, Relaxed);
        now
    }

    /// The bytes live now.
    pub fn live(&self) -> usize {
        self.live.load(Relaxed)
    }

    /// The most bytes live at once since the last [`Counting::reset_peak`].
    pub fn peak(&self) -> usize {
        self.peak.load(Relaxed)
    }

    fn grew(&self, by: usize) {
        let now = self.live.fetch_add(by, Relaxed) + by;
        self.peak.fetch_max(now, Relaxed);
    }
}

// SAFETY: every call is forwarded unchanged to `inner`; the counters only observe sizes.
unsafe impl<A: GlobalAlloc> GlobalAlloc for Counting<A> {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { self.inner.alloc(layout) };
        if !p.is_null() {
            self.grew(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { self.inner.alloc_zeroed(layout) };
        if !p.is_null() {
            self.grew(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { self.inner.dealloc(ptr, layout) };
        self.live.fetch_sub(layout.size(), Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { self.inner.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            self.live.fetch_sub(layout.size(), Relaxed);
            self.grew(new_size);
        }
        p
    }
}

unsafe extern "C" {
    fn mi_option_set(option: std::ffi::c_int, value: std::ffi::c_long);
}

/// `mi_option_purge_delay`: its place in mimalloc's `mi_option_t` (the same in its v2 and v3 headers;
/// the test below checks its default).
const PURGE_DELAY: std::ffi::c_int = 15;

/// Keep freed memory for reuse instead of handing it back to the system a second after it is freed
/// (mimalloc's default purge delay), unless `MIMALLOC_PURGE_DELAY` says otherwise. A training step frees
/// and allocates the same few hundred megabytes every second or so; handed back, each page faulted in
/// again and was zeroed by the kernel (`clear_page_erms`, 7.5% of a `mvmp bench train` profile), and the
/// demo's steps took 8-15% longer (README, Benchmarks). The resident size stays at the peak, which is
/// what the process needs anyway.
pub fn keep_freed_memory() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: sets one integer option of the allocator; any value is allowed at any time.
        unsafe { mi_option_set(PURGE_DELAY, -1) };
    }
}

#[cfg(test)]
mod tests {
    unsafe extern "C" {
        fn mi_option_get(option: std::ffi::c_int) -> std::ffi::c_long;
    }

    /// mimalloc's purge delay (milliseconds; -1: never).
    fn purge_delay() -> std::ffi::c_long {
        // SAFETY: reads one integer option.
        unsafe { mi_option_get(super::PURGE_DELAY) }
    }

    /// The option the binary sets is the purge delay: mimalloc's default for it is 1000 ms (v3; 10 in
    /// v2), no other option of v3 defaults to 1000, and setting it reads back.
    #[test]
    fn the_purge_delay_is_the_option_set() {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
            return;
        }
        assert!([10, 1000].contains(&purge_delay()));
        super::keep_freed_memory();
        assert_eq!(purge_delay(), -1);
    }
}

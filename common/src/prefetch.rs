//! Software prefetch of the cache lines a tick is about to touch.
//!
//! Between two ticks a role waits (blocked, or spinning on another core's data), and
//! the other roles on its core evict its lines: in a real-time run each line the next
//! tick touches first is a miss, one after another as the code reaches it. A prefetch
//! asks for them all at once, as soon as the tick's input is known to have come, so
//! that the misses overlap each other and the work still to be done before the input
//! is taken (the receive that finds no newer sample). It changes no value and no order:
//! only when the lines arrive.

/// Asks for every cache line of `value` (a hint: no fault, no wait, no effect on
/// correctness; nothing on targets without a prefetch instruction).
#[inline(always)]
pub fn lines<T: ?Sized>(value: &T) {
    each_line(value, |line| {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a prefetch never faults and reads nothing the program sees; the address
        // lies within (or on the line of) a live reference.
        unsafe {
            use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
            _mm_prefetch::<_MM_HINT_T0>(line as *const i8);
        }
    });
}

/// [`lines`] for lines about to be written: each asked for in the state that lets this
/// core write it (`prefetchw`), so a line another core holds (a subscriber read it last,
/// an observer polled it) is taken from it now, not at the store. Where the processor
/// has no `prefetchw` (CPUID `PRFCHW`), a read prefetch.
#[inline(always)]
pub fn lines_for_write<T: ?Sized>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    if has_prefetchw() {
        each_line(value, |line| {
            // SAFETY: as `lines`'s; `prefetchw` exists on this processor (CPUID checked),
            // reads nothing the program sees and writes nothing.
            unsafe {
                std::arch::asm!("prefetchw [{0}]", in(reg) line,
                                options(nostack, preserves_flags, readonly));
            }
        });
        return;
    }
    lines(value);
}

/// Calls `each` with the address of every 64-byte line `value` covers.
#[inline(always)]
fn each_line<T: ?Sized>(value: &T, mut each: impl FnMut(usize)) {
    let start = std::ptr::from_ref(value).cast::<u8>() as usize;
    let end = start + std::mem::size_of_val(value);
    let mut line = start & !63;
    while line < end {
        each(line);
        line += 64;
    }
}

/// Whether this processor has `prefetchw` (CPUID leaf 0x8000_0001, ECX bit 8), read once.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn has_prefetchw() -> bool {
    use std::sync::atomic::{AtomicU8, Ordering};
    static KNOWN: AtomicU8 = AtomicU8::new(0); // 0: not read yet, 1: no, 2: yes
    match KNOWN.load(Ordering::Relaxed) {
        0 => {
            // `cpuid` exists on every x86-64 processor (a safe intrinsic there); leaf
            // 0x8000_0001 is within the extended range every x86-64 processor reports.
            let ecx = std::arch::x86_64::__cpuid(0x8000_0001).ecx;
            let yes = ecx & (1 << 8) != 0;
            KNOWN.store(1 + u8::from(yes), Ordering::Relaxed);
            yes
        }
        k => k == 2,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lines asked for are exactly those `value` covers: the first is the line of its
    /// first byte, the last that of its last byte, none for an empty value.
    #[test]
    fn every_line_of_a_value_and_no_other_is_asked_for() {
        #[repr(align(64))]
        struct Lines([u8; 256]);
        let buf = Lines([0; 256]);
        let base = buf.0.as_ptr() as usize;
        for (a, b, want) in
            [(0, 0, 0), (0, 1, 1), (3, 70, 2), (63, 65, 2), (64, 128, 1), (1, 256, 4)]
        {
            let mut got = Vec::new();
            each_line(&buf.0[a..b], |line| got.push(line - base));
            let first = a / 64 * 64;
            assert_eq!(got, (0..want).map(|i| first + 64 * i).collect::<Vec<_>>(), "{a}..{b}");
            lines(&buf.0[a..b]);
            lines_for_write(&buf.0[a..b]);
        }
    }

    /// `prefetchw` is used where the kernel also sees it (`/proc/cpuinfo`'s
    /// `3dnowprefetch`, Linux's name for CPUID's `PRFCHW`).
    #[cfg(all(target_arch = "x86_64", target_os = "linux"))]
    #[test]
    fn prefetchw_is_found_where_the_kernel_finds_it() {
        let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").expect("/proc/cpuinfo");
        let flags = cpuinfo.lines().find(|l| l.starts_with("flags")).expect("a flags line");
        let kernel = flags.split_whitespace().any(|f| f == "3dnowprefetch");
        assert_eq!(has_prefetchw(), kernel, "{flags}");
        assert_eq!(has_prefetchw(), kernel, "the second reading, from the cache");
    }
}

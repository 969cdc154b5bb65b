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
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let start = std::ptr::from_ref(value).cast::<u8>() as usize;
        let end = start + std::mem::size_of_val(value);
        let mut line = start & !63;
        while line < end {
            // SAFETY: a prefetch never faults and reads nothing the program sees; the
            // address lies within (or on the line of) a live reference.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(line as *const i8) };
            line += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

//! What an older build's state sample looks like on the wire: another layout version.
//! Shared by `tests/hostile.rs` and, by path, `link/tests/gateway.rs` (a refusal on one
//! host and across the link must be the same refusal of the same sample).

use iceoryx2::prelude::ZeroCopySend;

/// A state sample of layout version 2.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("rotorloop::StateSample_v2")]
#[repr(C)]
pub struct StateSampleV2 {
    tick: u64,
    rest: [f64; 41],
}

//! rotorloop's link gateway (`rotorloop link`, binary `rotorloop-link`): carries one run
//! domain's services (`rotorloop/<domain>/…` only) between this host and another over
//! iceoryx2's own link (0.10) with its Zenoh carrier. It writes no transport of its own:
//! iceoryx2-link discovers the local services, mirrors the remote ones and copies the
//! sample bytes; this crate chooses what to bridge, builds and checks the Zenoh
//! configuration (who may connect, in which direction), and drives the link from one
//! thread, woken by the domain's own events and by the carrier.
//!
//! It is a crate of its own so that the four role binaries never link Zenoh (about 460
//! crates with tokio, quinn and rustls).

pub mod config;
pub mod gateway;
pub mod proof;

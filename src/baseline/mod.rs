//! What the loop is measured against and probed with, started as `rotorloop role …`
//! processes: the bench's paced ping-pong baselines and CPU hogs ([`pingpong`]), the
//! wake-up lateness of a bare thread on the plant's grid ([`timer`]), and the access probe
//! of the security tests ([`probe`]).

pub mod pingpong;
pub mod probe;
pub mod timer;

//! Wiring: the measurement of a frame set and the drivers around it — replay, live
//! (run / record / demo / replay --realtime), check and bench.

pub mod bench;
pub mod check;
pub mod journal;
pub mod live;
pub mod measure;
pub mod replay;

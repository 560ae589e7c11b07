//! The `citystream` command's small commands, beside the dispatcher (`main.rs`) that also
//! runs the other crates' commands: [`info`] (totals of a dataset), [`verify`] (every
//! offset, length and mip checked), [`cache_report`] (how a dataset packs into the sparse
//! cache), [`upgrade`] (older dataset formats rewritten), [`path`] (the standard camera path
//! written), [`merge`] (the shards of a sharded build joined into one dataset) and [`bind_replay`] (a run's sparse binds and copies, logged with
//! `CITYSTREAM_BIND_LOG`, replayed on the device).

pub mod bind_replay;
pub mod cache_report;
pub mod info;
pub mod merge;
pub mod path;
pub mod upgrade;
pub mod verify;

//! The `citystream` tool's commands as a library: the binary parses the
//! command line, and cross-crate tests drive the same commands directly
//! (for example, rendering a generated city and its atlas version).

pub mod atlas;
pub mod bench;
pub mod cache_report;
pub mod default_city;
pub mod fuzz;
pub mod gen;
pub mod import;
pub mod info;
pub mod loader_bench;
pub mod path;
pub mod report;
pub mod simulate;
pub mod upgrade;
pub mod verify;

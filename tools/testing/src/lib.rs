//! Testing aids: local servers for the remote tests and benchmarks ([`nginx`],
//! [`s3_emulator`], with [`server_process`] waiting for them to listen), a proxy that
//! injects faults between them and their clients ([`fault_proxy`]), and mutation harnesses
//! for every parser of untrusted input ([`fuzz`], run by the `fuzz` binary), and what the
//! tools' test crates share ([`tool_tests`]).

pub mod fault_proxy;
pub mod fuzz;
pub mod nginx;
pub mod s3_emulator;
pub mod server_process;
pub mod tool_tests;

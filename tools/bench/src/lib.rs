//! Benchmarks and their reports: [`bench`](mod@bench) (`citystream bench`, the flythrough
//! under several policies, strategies and scenarios; its runs in [`runs`], its tables and
//! checks in [`tables`], the paper's Berlin in [`berlin_bench`], speed against error over every
//! policy family in [`frontier`]), [`report`] (Table 3 and
//! Fig. 6 from flythrough runs, read by [`report_runs`]), [`image_error`] (the image-error
//! convention every figure uses, shared with the flythrough), [`simulate`] (the policy on
//! the modelled clock) and [`loader_bench`] / [`remote_bench`] (the loader from disk and
//! over HTTP), with [`disk_probe`] (this machine's disk for the read model).

pub mod bench;
pub mod berlin_bench;
pub mod disk_probe;
pub mod frontier;
pub mod image_error;
pub mod loader_bench;
pub mod remote_bench;
pub mod report;
pub mod report_runs;
pub mod runs;
pub mod simulate;
pub mod tables;

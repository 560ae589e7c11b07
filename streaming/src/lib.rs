//! Everything of citystream's streaming that needs no GPU: the paper's policy
//! (§3.4–3.5), the loader that carries it out, what is kept resident, and the
//! strategies and layers beside the paper's. Vulkan-free: the engine
//! (`citystream-engine`) carries out on the device what these modules decide;
//! the dataset the loader reads is `citystream-dataset`'s.
//!
//! The paper's pipeline:
//! - [`records`]: the feedback's per-mesh records, the τ cutoff and the sort
//!   by weight (§3.2–3.3).
//! - [`states`]: Algorithm 1's per-texture states (Initial, Active, Final) in
//!   one atomic word each, and the step that picks a texture's next level.
//! - [`controller`]: the adaptive controller (Eq. 4–7) and the other load
//!   policies behind [`controller::LoadPolicy`]: latency in, load size and
//!   mip bias out.
//! - [`loader`]: the streaming task, planning each cycle within the load size
//!   and reading exactly the mips planned on rayon's workers.
//! - [`disk_model`]: how long a cycle's reads take on a modelled disk, for the clocks
//!   that model time (a cycle then spans the frames its reads take).
//! - [`source`]: where mip bytes come from ([`source::MipSource`], with
//!   [`source::DatasetSource`] over a `citystream-dataset` pack) and where they go
//!   ([`source::MipSink`]).
//! - [`residency`]: what stays resident when the view needs more than the
//!   budget (the need table, keep values, the loader's admission gate) and
//!   [`residency::planner`], which levels and layers give way for each load,
//!   over any cache through [`residency::planner::ResidentCache`].
//! - [`bind_latency`]: a seeded model of what sparse binding costs on real
//!   drivers, wrapping a binder, so tests exercise the controller
//!   deterministically.
//!
//! The other strategies:
//! - [`atlas_tree`]: the texture-atlas tree (Buchholz & Döllner): its file,
//!   the traversal that picks nodes by distance and its paging.
//! - [`clipmap`] and [`ground`]: the flexible clipmap (Feldmann et al.) and
//!   the ground imagery composed from its patches.
//! - `bench` (feature `bench`): camera paths, the simulator on a modelled
//!   clock and run statistics, kept out of the core API.
//! - [`rng`]: the seeded generator behind the deterministic models.
#![forbid(unsafe_code)]

pub mod atlas_tree;
#[cfg(feature = "bench")]
pub mod bench;
pub mod bind_latency;
pub mod clipmap;
pub mod controller;
pub mod disk_model;
pub mod ground;
pub mod loader;
pub mod records;
pub mod residency;
pub mod rng;
pub mod shortfall;
pub mod source;
pub mod states;
pub mod tile_refinement;

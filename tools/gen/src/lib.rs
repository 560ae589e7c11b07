//! City generation: synthetic cities from presets ([`command`] is `citystream gen`, over
//! [`city`], the presets and the standard generator, and [`berlin`], the paper's Berlin),
//! the paper's §3.1 texture atlases ([`atlas`]), the texture-atlas tree ([`atlas_tree`]),
//! the default city the flythrough and the benchmarks open ([`default_city`]) and a
//! simulated aerial survey for the ground ([`patches`]).
//!
//! Below them, shared by the other tools' crates: [`texture`] (mip chains, BC1/BC3/BC7
//! encoding and decoding), [`library`] (user images: PNG, JPEG, DDS, KTX2) and
//! [`image_files`] (minimal KTX2/DDS writers), [`files`] (output replaced atomically,
//! stdout), [`location`] (datasets opened by directory or URL with the command line's
//! remote settings) and [`shard`] (`--shard I/N`: one shard of a sharded build, written
//! into a directory or S3).

pub mod atlas;
pub mod atlas_tree;
pub mod berlin;
pub mod city;
pub mod command;
pub mod default_city;
pub mod files;
pub mod image_files;
mod layout;
pub mod library;
pub mod location;
pub mod patches;
mod rng;
pub mod shard;
pub mod texture;

//! Import: glTF 2.0 scenes ([`gltf`]) and OGC 3D Tiles tilesets ([`tiles`], local or behind
//! HTTP and S3, with their geodesy and CRS placement) as datasets; [`command`] is
//! `citystream import`, which picks one by its input.
//!
//! Below them: [`transform`] (the 4×4 transforms both formats place meshes with) and
//! [`blocks`] (KTX2 and DDS sources whose BC blocks are kept).

pub mod blocks;
pub mod command;
pub mod gltf;
pub mod tiles;
pub mod transform;

//! Import: glTF 2.0 scenes ([`gltf`]) and OGC 3D Tiles tilesets ([`tiles`], local or behind
//! HTTP and S3, with their geodesy and CRS placement) as datasets; [`command`] is
//! `citystream import`, which picks one by its input.
//!
//! Below them: [`transform`] (the 4×4 transforms both formats place meshes with),
//! [`primitive`] (a glTF primitive in any of its encodings), [`decode`] (Draco, meshopt and
//! quantized geometry), [`blocks`] (KTX2 and DDS sources whose BC blocks are kept),
//! [`basis`] (Basis Universal KTX2 transcoded to BC blocks) and [`encodings`] (how many
//! meshes and textures came from each encoding, for `citystream info`).

pub mod basis;
pub mod blocks;
pub mod command;
pub mod decode;
pub mod encodings;
pub mod gltf;
pub mod primitive;
pub mod tiles;
pub mod transform;

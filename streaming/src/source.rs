//! Where mip bytes come from ([`MipSource`]) and where staged mips go
//! ([`MipSink`]), with in-memory implementations for tests and tools.
//!
//! The file-backed dataset reader ([`DatasetSource`]) implements
//! [`MipSource`] with one positioned read per mip; the engine's uploader implements [`MipSink`]
//! (records the copy into the sparse image and the memory binding).
//!
//! Everything a [`MipSource`]'s signatures name is here: [`TextureFormat`]
//! and [`MipChain`] are re-exported, so a host implementing its own source
//! needs no dependency on `citystream-dataset`.

use std::sync::{Arc, Mutex};

use citystream_cache::geometry::cacheable_mip_count;
use citystream_cache::TexelFormat;

pub use crate::states::MipChain;
/// The formats a source's mips are stored in (`citystream-dataset`'s), re-exported for
/// [`MipSource::texture_format`].
pub use citystream_dataset::TextureFormat;
use citystream_dataset::{Dataset, DatasetError};

/// Error reading a texture's header or a mip.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// No such texture in the source.
    #[error("texture {texture} does not exist in the source")]
    UnknownTexture {
        /// The texture asked for.
        texture: u32,
    },
    /// The level is beyond the texture's mip chain.
    #[error("texture {texture} has {mip_count} mip levels; level {level} does not exist")]
    UnknownLevel {
        /// The texture.
        texture: u32,
        /// The level asked for.
        level: u32,
        /// Levels the texture has.
        mip_count: u32,
    },
    /// The buffer does not match the mip's length.
    #[error("texture {texture} level {level} is {expected} bytes; buffer holds {got}")]
    LengthMismatch {
        /// The texture.
        texture: u32,
        /// The level.
        level: u32,
        /// Bytes the mip has.
        expected: u64,
        /// Bytes the buffer has.
        got: u64,
    },
    /// The file ended before the mip did.
    #[error("short read of texture {texture} level {level}: {got} of {expected} bytes")]
    ShortRead {
        /// The texture.
        texture: u32,
        /// The level.
        level: u32,
        /// Bytes wanted.
        expected: u64,
        /// Bytes read.
        got: u64,
    },
    /// Any other I/O failure (missing file, permissions, device error).
    #[error("reading texture {texture} level {level}: {source}")]
    Io {
        /// The texture.
        texture: u32,
        /// The level.
        level: u32,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// An I/O failure reading a named file.
    #[error("reading texture {texture} level {level} from {}: {source}", path.display())]
    File {
        /// The texture.
        texture: u32,
        /// The level.
        level: u32,
        /// The file read.
        path: std::path::PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// Anything else the source reports, already worded.
    #[error("texture {texture}: {reason}")]
    Other {
        /// The texture.
        texture: u32,
        /// What went wrong.
        reason: String,
    },
}

/// Reads texture headers and exactly one mip at a time.
///
/// Threading: called concurrently from loader worker threads (`Sync`);
/// implementations use positioned reads, not a shared cursor.
pub trait MipSource: Send + Sync {
    /// How many textures the source holds; ids run `0..texture_count()`.
    fn texture_count(&self) -> u32;
    /// The format `texture`'s mips are stored in, as [`MipSource::read_mip`]
    /// returns them (the GPU cache stores them unchanged).
    fn texture_format(&self, texture: u32) -> Result<TextureFormat, SourceError>;
    /// Extent and mip count of `texture` (`LoadImageMetaDatum`).
    fn mip_chain(&self, texture: u32) -> Result<MipChain, SourceError>;
    /// Bytes of `level` of `texture`.
    fn mip_len(&self, texture: u32, level: u32) -> Result<u64, SourceError>;
    /// Read `level` of `texture` into `buf`, whose length must equal
    /// [`MipSource::mip_len`]; a shorter file is [`SourceError::ShortRead`].
    fn read_mip(&self, texture: u32, level: u32, buf: &mut [u8]) -> Result<(), SourceError>;

    /// The mips the loader is about to read this cycle, highest priority first: a source
    /// with high latency (a remote store) starts fetching them now, many at once, so that
    /// [`MipSource::read_mip`] finds them ready. A hint only: reads of mips not hinted, or
    /// hinted and then not read, behave as without it. The default does nothing.
    fn prefetch(&self, _mips: &[(u32, u32)]) {}

    /// [`SourceError::LengthMismatch`] unless `buf` holds exactly the
    /// mip's bytes: the check every [`MipSource::read_mip`] starts with.
    fn check_buffer_len(&self, texture: u32, level: u32, buf: &[u8]) -> Result<(), SourceError> {
        let expected = self.mip_len(texture, level)?;
        if buf.len() as u64 != expected {
            return Err(SourceError::LengthMismatch {
                texture,
                level,
                expected,
                got: buf.len() as u64,
            });
        }
        Ok(())
    }
}

/// A mip read from the source, handed to the sink.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StagedMip {
    /// The texture.
    pub texture: u32,
    /// The level (0 = base).
    pub level: u32,
    /// The mip's bytes, exactly as stored.
    pub bytes: Vec<u8>,
}

/// Error from a sink. With `invalidated` set (the cache reused the
/// texture's region while the mip was being loaded) the loader invalidates
/// the texture, so it is unloaded and later loaded again; otherwise it
/// marks the texture failed. Either way the cycle goes on.
#[derive(Debug, thiserror::Error)]
#[error("sink rejected texture {texture} level {level}: {reason}")]
pub struct SinkError {
    /// The texture.
    pub texture: u32,
    /// The level.
    pub level: u32,
    /// Why.
    pub reason: String,
    /// The texture's cache region is gone; not a failure of the texture.
    pub invalidated: bool,
}

/// Receives staged mips (`CopyToSparseImage`) and unload requests
/// (`UnloadTextures`).
///
/// Threading: `stage` is called concurrently from loader workers during a
/// cycle; `unload` and `end_cycle` from the cycle's own thread, `unload`
/// before any `stage` of that cycle and `end_cycle` after the last one.
pub trait MipSink: Send + Sync {
    /// Take one loaded mip (record its copy and binding).
    fn stage(&self, mip: StagedMip) -> Result<(), SinkError>;
    /// Make an invalidated texture unsampleable in the shader.
    fn unload(&self, texture: u32);
    /// The cycle is over: submit what was recorded. Default: nothing.
    fn end_cycle(&self) {}
    /// Take one loaded mip whose read completes `done` after its cycle started on a
    /// modelled disk ([`crate::loader::LoaderOptions::disk`]); a host with a modelled
    /// clock holds it until then. Default: [`stage`](Self::stage) at once.
    fn stage_after(&self, mip: StagedMip, done: std::time::Duration) -> Result<(), SinkError> {
        let _ = done;
        self.stage(mip)
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    // A panic while holding the lock cannot leave these plain vectors
    // half-updated, so the data stays usable.
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A sink that keeps everything in memory, for tests and tools.
#[derive(Debug, Default)]
pub struct MemorySink {
    staged: Mutex<Vec<StagedMip>>,
    unloaded: Mutex<Vec<u32>>,
    cycles: Mutex<u64>,
}

impl MemorySink {
    /// An empty sink.
    pub fn new() -> Self {
        Self::default()
    }

    /// Take the mips staged so far.
    pub fn take_staged(&self) -> Vec<StagedMip> {
        std::mem::take(&mut *lock(&self.staged))
    }

    /// Textures unloaded so far, in call order.
    pub fn unloaded(&self) -> Vec<u32> {
        lock(&self.unloaded).clone()
    }

    /// Cycles ended so far.
    pub fn cycles(&self) -> u64 {
        *lock(&self.cycles)
    }
}

impl MipSink for MemorySink {
    fn stage(&self, mip: StagedMip) -> Result<(), SinkError> {
        lock(&self.staged).push(mip);
        Ok(())
    }

    fn unload(&self, texture: u32) {
        lock(&self.unloaded).push(texture);
    }

    fn end_cycle(&self) {
        *lock(&self.cycles) += 1;
    }
}

/// Bytes of a BC1 (8 bytes per 4×4 block) mip of the given extent.
pub fn bc1_mip_len(width: u32, height: u32) -> u64 {
    u64::from(width.div_ceil(4)) * u64::from(height.div_ceil(4)) * 8
}

/// A source holding BC1 mip chains in memory; each byte is a function of
/// (texture, level, offset) so tests can check what arrived. Mips can be
/// removed or truncated to inject the failures a file source would have.
#[derive(Debug, Default)]
pub struct MemorySource {
    textures: Vec<MemoryTexture>,
}

#[derive(Debug)]
struct MemoryTexture {
    chain: MipChain,
    mips: Vec<Option<Vec<u8>>>,
}

/// The byte [`MemorySource`] stores at `offset` of `level` of `texture`.
pub fn pattern_byte(texture: u32, level: u32, offset: usize) -> u8 {
    (texture.wrapping_mul(31) ^ level.wrapping_mul(7) ^ offset as u32) as u8
}

impl MemorySource {
    /// An empty source.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add a full BC1 mip chain of `width`×`height`; returns its id.
    pub fn push_bc1(&mut self, width: u32, height: u32) -> u32 {
        let id = self.textures.len() as u32;
        let width = width.max(1);
        let height = height.max(1);
        let mip_count = 32 - width.max(height).leading_zeros();
        let chain = MipChain {
            width,
            height,
            mip_count,
        };
        let mips = (0..mip_count)
            .map(|level| {
                let (w, h) = chain.level_extent(level);
                let len = bc1_mip_len(w, h) as usize;
                Some((0..len).map(|o| pattern_byte(id, level, o)).collect())
            })
            .collect();
        self.textures.push(MemoryTexture { chain, mips });
        id
    }

    /// Make `level` of `texture` missing (reads fail with an I/O error).
    pub fn remove_mip(&mut self, texture: u32, level: u32) {
        if let Some(m) = self
            .textures
            .get_mut(texture as usize)
            .and_then(|t| t.mips.get_mut(level as usize))
        {
            *m = None;
        }
    }

    /// Cut `level` of `texture` to `len` bytes (reads fail as short reads).
    pub fn truncate_mip(&mut self, texture: u32, level: u32, len: usize) {
        if let Some(Some(m)) = self
            .textures
            .get_mut(texture as usize)
            .and_then(|t| t.mips.get_mut(level as usize))
        {
            m.truncate(len);
        }
    }

    fn texture(&self, texture: u32) -> Result<&MemoryTexture, SourceError> {
        self.textures
            .get(texture as usize)
            .ok_or(SourceError::UnknownTexture { texture })
    }
}

impl MipSource for MemorySource {
    fn texture_count(&self) -> u32 {
        self.textures.len() as u32
    }

    fn texture_format(&self, texture: u32) -> Result<TextureFormat, SourceError> {
        self.texture(texture).map(|_| TextureFormat::Bc1)
    }

    fn mip_chain(&self, texture: u32) -> Result<MipChain, SourceError> {
        Ok(self.texture(texture)?.chain)
    }

    fn mip_len(&self, texture: u32, level: u32) -> Result<u64, SourceError> {
        let t = self.texture(texture)?;
        if level >= t.chain.mip_count {
            return Err(SourceError::UnknownLevel {
                texture,
                level,
                mip_count: t.chain.mip_count,
            });
        }
        let (w, h) = t.chain.level_extent(level);
        Ok(bc1_mip_len(w, h))
    }

    fn read_mip(&self, texture: u32, level: u32, buf: &mut [u8]) -> Result<(), SourceError> {
        self.check_buffer_len(texture, level, buf)?;
        let expected = buf.len() as u64;
        let stored = self
            .texture(texture)?
            .mips
            .get(level as usize)
            .and_then(Option::as_ref)
            .ok_or_else(|| SourceError::Io {
                texture,
                level,
                source: std::io::Error::new(std::io::ErrorKind::NotFound, "mip data missing"),
            })?;
        if (stored.len() as u64) < expected {
            return Err(SourceError::ShortRead {
                texture,
                level,
                expected,
                got: stored.len() as u64,
            });
        }
        buf.copy_from_slice(&stored[..buf.len()]);
        Ok(())
    }
}

/// Which reads a [`FaultySource`] fails: the mips whose `(texture, level)`
/// hash falls on one in `every`, each for its first `times` reads. The
/// choice depends on the mip, not on read order, so runs with parallel
/// readers fail the same mips.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FaultPlan {
    /// One mip in this many fails (1: every mip).
    pub every: u32,
    /// Reads of such a mip that fail before one succeeds (`u32::MAX`:
    /// never succeeds).
    pub times: u32,
    /// How the failing reads fail.
    pub kind: FaultKind,
}

/// How an injected read failure looks to the loader.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FaultKind {
    /// An I/O error.
    Error,
    /// The read ends early ([`SourceError::ShortRead`]).
    ShortRead,
}

impl FaultPlan {
    /// Parses `EVERY:TIMES` (both at least 1), failing with I/O errors.
    pub fn parse(text: &str) -> Result<Self, String> {
        let (every, times) = text
            .split_once(':')
            .ok_or_else(|| format!("`{text}` is not EVERY:TIMES (e.g. 5:2)"))?;
        let number = |part: &str, what: &str| match part.trim().parse::<u32>() {
            Ok(n) if n >= 1 => Ok(n),
            _ => Err(format!("{what} in `{text}` must be a whole number of at least 1")),
        };
        Ok(FaultPlan {
            every: number(every, "EVERY")?,
            times: number(times, "TIMES")?,
            kind: FaultKind::Error,
        })
    }

    fn hits(&self, texture: u32, level: u32) -> bool {
        // SplitMix64's finaliser: neighbouring mips land far apart.
        let mut z = (u64::from(texture) << 32 | u64::from(level)).wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        z % u64::from(self.every.max(1)) == 0
    }
}

/// A [`MipSource`] that fails chosen reads of another, to test how the
/// loader and the engine handle failures (and for `flythrough
/// --inject-read-failures`). Without a plan it reads straight through.
#[derive(Debug)]
pub struct FaultySource<S> {
    inner: S,
    plan: Option<FaultPlan>,
    /// Named in the injected errors, as a file source would name its file.
    file: std::path::PathBuf,
    /// Failed reads so far, per `(texture, level)`.
    failed_reads: Mutex<std::collections::HashMap<(u32, u32), u32>>,
}

impl<S: MipSource> FaultySource<S> {
    /// Wraps `inner`; `file` is named in injected errors.
    pub fn new(inner: S, plan: Option<FaultPlan>, file: impl Into<std::path::PathBuf>) -> Self {
        FaultySource {
            inner,
            plan,
            file: file.into(),
            failed_reads: Mutex::new(std::collections::HashMap::new()),
        }
    }

    /// The wrapped source.
    pub fn inner(&self) -> &S {
        &self.inner
    }

    /// Reads failed on purpose so far.
    pub fn injected_failures(&self) -> u64 {
        lock(&self.failed_reads).values().map(|&n| u64::from(n)).sum()
    }
}

impl<S: MipSource> MipSource for FaultySource<S> {
    fn texture_count(&self) -> u32 {
        self.inner.texture_count()
    }

    fn texture_format(&self, texture: u32) -> Result<TextureFormat, SourceError> {
        self.inner.texture_format(texture)
    }

    fn mip_chain(&self, texture: u32) -> Result<MipChain, SourceError> {
        self.inner.mip_chain(texture)
    }

    fn mip_len(&self, texture: u32, level: u32) -> Result<u64, SourceError> {
        self.inner.mip_len(texture, level)
    }

    fn prefetch(&self, mips: &[(u32, u32)]) {
        self.inner.prefetch(mips);
    }

    fn read_mip(&self, texture: u32, level: u32, buf: &mut [u8]) -> Result<(), SourceError> {
        if let Some(plan) = self.plan.filter(|plan| plan.hits(texture, level)) {
            let mut failed = lock(&self.failed_reads);
            let count = failed.entry((texture, level)).or_insert(0);
            if *count < plan.times {
                *count += 1;
                return Err(match plan.kind {
                    FaultKind::Error => SourceError::File {
                        texture,
                        level,
                        path: self.file.clone(),
                        source: std::io::Error::other(format!("injected read failure {count} of {}", plan.times)),
                    },
                    FaultKind::ShortRead => SourceError::ShortRead {
                        texture,
                        level,
                        expected: buf.len() as u64,
                        got: buf.len() as u64 / 2,
                    },
                });
            }
        }
        self.inner.read_mip(texture, level, buf)
    }
}

/// The cache's texel format for a dataset format.
pub fn texel_format(format: TextureFormat) -> TexelFormat {
    match format {
        TextureFormat::Bc1 => TexelFormat::BC1,
        TextureFormat::Bc3 => TexelFormat::BC3,
        TextureFormat::Bc7 => TexelFormat::BC7,
        TextureFormat::Rgba8 => TexelFormat::RGBA8,
    }
}

/// The dataset's texture pack as a [`MipSource`]. The chain it reports
/// stops at the levels the cache can hold (both sides at least one texel
/// block), so the loader never asks for a level the cache would refuse.
#[derive(Debug, Clone)]
pub struct DatasetSource {
    dataset: Arc<Dataset>,
}

impl DatasetSource {
    /// Reads from `dataset`.
    pub fn new(dataset: Arc<Dataset>) -> Self {
        Self { dataset }
    }

    /// The dataset read from.
    pub fn dataset(&self) -> &Arc<Dataset> {
        &self.dataset
    }

    fn chain(&self, texture: u32) -> Result<MipChain, SourceError> {
        let info = self
            .dataset
            .textures
            .info(texture)
            .map_err(|_| SourceError::UnknownTexture { texture })?;
        let cacheable = cacheable_mip_count(&texel_format(info.format()), info.width(), info.height());
        Ok(MipChain {
            width: info.width(),
            height: info.height(),
            mip_count: info.mip_count().min(cacheable).max(1),
        })
    }
}

fn source_error(texture: u32, level: u32, error: DatasetError) -> SourceError {
    match error {
        DatasetError::Io { path, source } => SourceError::File {
            texture,
            level,
            path,
            source,
        },
        other => SourceError::Other {
            texture,
            reason: other.to_string(),
        },
    }
}

impl MipSource for DatasetSource {
    fn texture_count(&self) -> u32 {
        self.dataset.textures.len()
    }

    fn texture_format(&self, texture: u32) -> Result<TextureFormat, SourceError> {
        self.dataset
            .textures
            .info(texture)
            .map(|info| info.format())
            .map_err(|_| SourceError::UnknownTexture { texture })
    }

    fn mip_chain(&self, texture: u32) -> Result<MipChain, SourceError> {
        self.chain(texture)
    }

    fn mip_len(&self, texture: u32, level: u32) -> Result<u64, SourceError> {
        let chain = self.chain(texture)?;
        if level >= chain.mip_count {
            return Err(SourceError::UnknownLevel {
                texture,
                level,
                mip_count: chain.mip_count,
            });
        }
        let info = self
            .dataset
            .textures
            .info(texture)
            .map_err(|_| SourceError::UnknownTexture { texture })?;
        Ok(info.mip_len(level))
    }

    fn prefetch(&self, mips: &[(u32, u32)]) {
        self.dataset.textures.prefetch(mips);
    }

    fn read_mip(&self, texture: u32, level: u32, buf: &mut [u8]) -> Result<(), SourceError> {
        self.check_buffer_len(texture, level, buf)?;
        self.dataset
            .textures
            .read_mip_into(texture, level, buf)
            .map(|_| ())
            .map_err(|e| source_error(texture, level, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bc1_sizes_by_hand() {
        // 512² BC1: 128·128 blocks · 8 B = 131072 B; 4×4 and 1×1 are one block.
        assert_eq!(bc1_mip_len(512, 512), 131_072);
        assert_eq!(bc1_mip_len(4, 4), 8);
        assert_eq!(bc1_mip_len(1, 1), 8);
        assert_eq!(bc1_mip_len(4, 32), 64);
    }

    #[test]
    fn memory_source_reads_and_fails_as_files_do() {
        let mut s = MemorySource::new();
        let t = s.push_bc1(16, 16);
        assert_eq!(s.mip_chain(t).map(|c| c.mip_count).ok(), Some(5));
        let mut buf = vec![0; 32];
        assert!(s.read_mip(t, 0, &mut buf).is_err(), "wrong length");
        let mut buf = vec![0; 128];
        s.read_mip(t, 0, &mut buf).expect("present");
        assert_eq!(buf[5], pattern_byte(t, 0, 5));
        s.truncate_mip(t, 0, 100);
        assert!(matches!(
            s.read_mip(t, 0, &mut buf),
            Err(SourceError::ShortRead { got: 100, .. })
        ));
        s.remove_mip(t, 1);
        let mut buf = vec![0; 32];
        assert!(matches!(s.read_mip(t, 1, &mut buf), Err(SourceError::Io { .. })));
        assert!(matches!(
            s.mip_len(t, 5),
            Err(SourceError::UnknownLevel { mip_count: 5, .. })
        ));
        assert!(matches!(
            s.mip_chain(9),
            Err(SourceError::UnknownTexture { texture: 9 })
        ));
    }
}

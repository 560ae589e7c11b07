//! The Vulkan implementation of the cache's [`SparseBinder`]: one
//! `vkQueueBindSparse` per batch, adjacent blocks merged, a timeline
//! semaphore value signalled that the copy submission waits on.
//!
//! With the bind checker on ([`checks_binds`]: `CITYSTREAM_CHECK_BINDS=1`,
//! and by default in debug builds, so in the tests), every batch and every
//! copy into the images is checked against a CPU shadow of their page tables
//! and of the memory chunks ([`citystream_cache::BindChecker`]) before it
//! reaches the driver; a violation fails the call, naming the image, layer,
//! level and block. Chunks are freed only when the binder is dropped, after
//! the device idles and after the images it binds (field order below).
//!
//! With `CITYSTREAM_BIND_LOG=FILE` the binder also writes every image, chunk,
//! batch and copy it is asked for to FILE, flushed as it goes, so that what
//! led up to a driver fault can be replayed (`citystream bind-replay FILE`;
//! format in [`bind_log`]).

use std::io::Write;
use std::sync::Arc;
use std::time::Instant;

use ash::vk;
use citystream_cache::{BindChecker, BindError, BindOp, BindReport, ImageShape, MipTail, SparseBinder};

use crate::commands::{SemaphoreWait, TimelineSemaphore};
use crate::device::Device;
use crate::error::EngineError;
use crate::error::Result;
use crate::sparse::{submit_bind_sparse_after, SparseBlockBind, SparseImage, SparseMemoryChunk, TailBind, TexelUpload};

/// Whether binders check binds and copies: `CITYSTREAM_CHECK_BINDS` = `1` on,
/// `0` off; unset, on in debug builds and off in release builds.
pub fn checks_binds() -> bool {
    match std::env::var("CITYSTREAM_CHECK_BINDS").as_deref() {
        Ok("1") => true,
        Ok("0") => false,
        _ => cfg!(debug_assertions),
    }
}

/// Binds cache blocks into sparse images from pooled memory chunks.
///
/// `BindOp::block.image` indexes the images given at creation;
/// `MemorySlot::chunk` indexes the chunks added with [`VulkanBinder::add_chunk`].
/// Threading: owned by one thread at a time (the streaming task).
pub struct VulkanBinder {
    device: Arc<Device>,
    images: Vec<Arc<SparseImage>>,
    chunks: Vec<SparseMemoryChunk>,
    timeline: TimelineSemaphore,
    signalled: u64,
    checker: Option<BindChecker>,
    log: Option<BindLog>,
}

/// The block grid and mip tail of `image`, as the bind checker sees it.
pub fn image_shape(image: &SparseImage) -> ImageShape {
    let desc = image.desc();
    let tail = cache_mip_tail(image);
    let block_levels = tail.map_or(desc.mips, |tail| tail.first_level);
    ImageShape {
        layers: desc.layers,
        level_blocks: (0..block_levels).map(|level| image.level_blocks(level)).collect(),
        mip_tail: tail,
    }
}

/// The mip tail of `image` in the cache's terms (`None` without one).
pub fn cache_mip_tail(image: &SparseImage) -> Option<MipTail> {
    let tail = image.mip_tail();
    (tail.first_lod < image.desc().mips).then(|| MipTail {
        first_level: tail.first_lod,
        blocks: image.tail_blocks(),
        single: tail.single,
    })
}

/// The bind log being written (see [`bind_log`]).
struct BindLog {
    path: std::path::PathBuf,
    /// The absolute path, as held in [`open_bind_logs`].
    key: std::path::PathBuf,
    out: std::io::BufWriter<std::fs::File>,
}

/// The bind logs this process's binders write, by absolute path (a few at
/// most: a list will do).
fn open_bind_logs() -> std::sync::MutexGuard<'static, Vec<std::path::PathBuf>> {
    static OPEN: std::sync::Mutex<Vec<std::path::PathBuf>> = std::sync::Mutex::new(Vec::new());
    OPEN.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

debug_fields!(VulkanBinder {
    images = |s| s.images.len(),
    chunks = |s| s.chunks.len(),
    signalled,
    checks_binds = |s| s.checker.is_some(),
});

impl VulkanBinder {
    /// A binder for `images` with no memory chunks yet, checking its binds
    /// where [`checks_binds`] says so.
    pub fn new(device: &Arc<Device>, images: Vec<Arc<SparseImage>>) -> Result<Self> {
        Self::with_checks(device, images, checks_binds())
    }

    /// As [`new`](Self::new), with the bind checker on or off whatever the
    /// environment says (the bind log still follows `CITYSTREAM_BIND_LOG`).
    pub fn with_checks(device: &Arc<Device>, images: Vec<Arc<SparseImage>>, check: bool) -> Result<Self> {
        let checker = check.then(|| {
            // The cache's images share one block size (it refuses others).
            let mut checker = BindChecker::new(images.first().map_or(1, |image| image.block_size()));
            for image in &images {
                checker.add_image(image_shape(image));
            }
            checker
        });
        let mut binder = Self {
            device: Arc::clone(device),
            images,
            chunks: Vec::new(),
            timeline: TimelineSemaphore::new(device, 0, "sparse binds")?,
            signalled: 0,
            checker,
            log: None,
        };
        if let Some(path) = std::env::var_os("CITYSTREAM_BIND_LOG").filter(|p| !p.is_empty()) {
            binder.start_log(path.into())?;
        }
        Ok(binder)
    }

    /// Writes the bind log to `path` from here on, starting with the images;
    /// unless another binder of this process writes `path` already (the
    /// flythrough's error reference beside the streamed cache): one writer a
    /// log, the first, so the two never interleave or truncate each other.
    fn start_log(&mut self, path: std::path::PathBuf) -> Result<()> {
        let key = std::path::absolute(&path).unwrap_or_else(|_| path.clone());
        {
            let mut open = open_bind_logs();
            if open.contains(&key) {
                return Ok(());
            }
            open.push(key.clone());
        }
        let file = match std::fs::File::create(&path) {
            Ok(file) => file,
            Err(source) => {
                open_bind_logs().retain(|open| *open != key);
                return Err(EngineError::BindLog {
                    path: path.display().to_string(),
                    source,
                });
            }
        };
        let mut text = format!("{}\n", bind_log::HEADER);
        for (index, image) in self.images.iter().enumerate() {
            let desc = image.desc();
            let (gw, gh) = image.granularity();
            let tail = cache_mip_tail(image);
            text += &format!(
                "image {index} {} {} {} {} {} {gw} {gh} {} {} {} {}\n",
                desc.width,
                desc.height,
                desc.layers,
                desc.mips,
                desc.format.as_raw(),
                image.block_size(),
                tail.map_or(desc.mips, |t| t.first_level),
                tail.map_or(0, |t| t.blocks),
                u8::from(tail.is_some_and(|t| t.single)),
            );
        }
        self.log = Some(BindLog {
            path,
            key,
            out: std::io::BufWriter::new(file),
        });
        self.write_log(&text)
    }

    /// Whether this binder writes the bind log (`CITYSTREAM_BIND_LOG`): false
    /// without one, or where another binder of the process writes it.
    pub fn writes_bind_log(&self) -> bool {
        self.log.is_some()
    }

    /// Appends `text` to the bind log, if one is written, and flushes it.
    fn write_log(&mut self, text: &str) -> Result<()> {
        let Some(log) = &mut self.log else {
            return Ok(());
        };
        log.out
            .write_all(text.as_bytes())
            .and_then(|()| log.out.flush())
            .map_err(|source| EngineError::BindLog {
                path: log.path.display().to_string(),
                source,
            })
    }

    /// Adds a memory chunk; returns its index for `MemorySlot::chunk`.
    pub fn add_chunk(&mut self, chunk: SparseMemoryChunk) -> Result<u32> {
        if let Some(checker) = &mut self.checker {
            checker.add_chunk(chunk.size());
        }
        let index = self.chunks.len() as u32;
        self.write_log(&format!("chunk {index} {}\n", chunk.size()))?;
        self.chunks.push(chunk);
        Ok(index)
    }

    /// Batches and block operations the checker passed so far; `None` with it off.
    pub fn checked(&self) -> Option<(u64, u64)> {
        self.checker.as_ref().map(BindChecker::checked)
    }

    /// Before `upload` is recorded into image `image`: logs it where a bind
    /// log is written and, with the checker on, refuses it unless every block
    /// it writes is bound (after the batches submitted so far).
    pub fn check_copy(&mut self, image: u32, upload: &TexelUpload) -> Result<()> {
        self.write_log(&format!(
            "copy {image} {} {} {} {} {} {}\n",
            upload.layer, upload.mip, upload.x, upload.y, upload.width, upload.height
        ))?;
        let (Some(checker), Some(target)) = (&self.checker, self.images.get(image as usize)) else {
            return Ok(());
        };
        let (gw, gh) = target.granularity();
        let columns = upload.x / gw.max(1)..(upload.x + upload.width).div_ceil(gw.max(1));
        let rows = upload.y / gh.max(1)..(upload.y + upload.height).div_ceil(gh.max(1));
        checker
            .check_copy(image, upload.layer, upload.mip, columns, rows)
            .map_err(|violation| EngineError::InvalidRequest(format!("sparse bind check: {violation}")))
    }

    /// What a submission that reads the bound blocks must wait on: the
    /// timeline value of the last batch.
    pub fn wait_for_last_batch(&self, stages: vk::PipelineStageFlags2) -> SemaphoreWait {
        SemaphoreWait {
            semaphore: self.timeline.raw(),
            stages,
            value: self.signalled,
        }
    }

    /// The timeline value signalled by the last batch (0 before any).
    pub fn last_signalled(&self) -> u64 {
        self.signalled
    }

    /// Blocks the host until every batch submitted so far has been carried out.
    pub fn wait_for_batches(&self) -> Result<()> {
        if self.signalled == 0 {
            return Ok(());
        }
        self.timeline.wait(self.signalled)
    }

    fn resolve(&self, op: &BindOp) -> std::result::Result<(usize, Resolved), BindError> {
        let block = op.block();
        let image = self
            .images
            .get(block.image as usize)
            .ok_or(BindError::UnknownBlock { block })?;
        let memory = match op {
            BindOp::Unbind { .. } => None,
            BindOp::Bind { memory, .. } => {
                let chunk = self
                    .chunks
                    .get(memory.chunk as usize)
                    .ok_or_else(|| BindError::Rejected {
                        blocks: 1,
                        reason: format!(
                            "memory chunk {} does not exist ({} chunks)",
                            memory.chunk,
                            self.chunks.len()
                        ),
                    })?;
                Some(
                    chunk
                        .at(memory.offset, image.block_size())
                        .ok_or_else(|| BindError::Rejected {
                            blocks: 1,
                            reason: format!(
                                "offset {} is not a block-aligned offset inside chunk {} of {} bytes",
                                memory.offset,
                                memory.chunk,
                                chunk.size()
                            ),
                        })?,
                )
            }
        };
        let first_tail_lod = image.mip_tail().first_lod;
        if !block.is_tail() && block.mip >= first_tail_lod && first_tail_lod < image.desc().mips {
            return Err(BindError::Rejected {
                blocks: 1,
                reason: format!(
                    "image {} layer {} level {} block ({}, {}): levels from {first_tail_lod} on are in the mip tail, \
                     bound as a whole, not per block",
                    block.image, block.layer, block.mip, block.x, block.y
                ),
            });
        }
        if block.is_tail() {
            let bind = image
                .tail_bind(block.layer, block.x, memory)
                .map_err(|e| BindError::Rejected {
                    blocks: 1,
                    reason: e.to_string(),
                })?;
            return Ok((
                block.image as usize,
                match bind {
                    TailBind::Opaque(bind) => Resolved::Opaque(bind),
                    TailBind::Block(block) => Resolved::Block(block),
                },
            ));
        }
        Ok((
            block.image as usize,
            Resolved::Block(SparseBlockBind {
                layer: block.layer,
                mip: block.mip,
                x: block.x,
                y: block.y,
                memory,
            }),
        ))
    }
}

impl VulkanBinder {
    /// Submits `batch` as one `vkQueueBindSparse` that starts on the GPU
    /// only after the previous batch (so memory an earlier unbind freed is
    /// never bound twice at once) and after `frames` (a frame timeline
    /// value) when given: unbinds must not race frames still sampling.
    /// Errors: the driver's (device lost, out of memory, named as such), or
    /// `InvalidRequest` for a batch naming unknown images, chunks or offsets.
    pub fn submit_after(&mut self, batch: &[BindOp], frames: Option<SemaphoreWait>) -> Result<BindReport> {
        self.submit_ops(batch, frames).map_err(|e| match e {
            SubmitError::Batch(e) => EngineError::InvalidRequest(format!("sparse bind: {e}")),
            SubmitError::Device(e) => e,
        })
    }

    fn submit_ops(
        &mut self,
        batch: &[BindOp],
        frames: Option<SemaphoreWait>,
    ) -> std::result::Result<BindReport, SubmitError> {
        if batch.is_empty() {
            return Ok(BindReport::default());
        }
        let mut per_image: Vec<Vec<SparseBlockBind>> = vec![Vec::new(); self.images.len()];
        let mut opaque_per_image: Vec<Vec<vk::SparseMemoryBind>> = vec![Vec::new(); self.images.len()];
        let mut tail_blocks = vec![0usize; self.images.len()];
        for op in batch {
            let (image, bind) = self.resolve(op).map_err(SubmitError::Batch)?;
            match bind {
                Resolved::Block(block) => {
                    per_image[image].push(block);
                    tail_blocks[image] += usize::from(op.block().is_tail());
                }
                Resolved::Opaque(bind) => opaque_per_image[image].push(bind),
            }
        }
        let mut entries = Vec::with_capacity(self.images.len());
        for ((image, binds), &tail) in self.images.iter().zip(&per_image).zip(&tail_blocks) {
            // A synthetic tail's blocks are its levels' blocks; other blocks
            // of tail levels are refused.
            let built = if tail > 0 {
                image.bind_entries_with_synthetic_tail(binds)
            } else {
                image.bind_entries(binds)
            };
            let image_entries = built.map_err(|e| {
                SubmitError::Batch(BindError::Rejected {
                    blocks: binds.len() as u32,
                    reason: e.to_string(),
                })
            })?;
            entries.push((image.raw(), image_entries));
        }
        // Checked last, once the batch is well formed, so that it reaches the
        // driver exactly when the shadow takes it.
        if let Some(checker) = &mut self.checker {
            checker.check_batch(batch).map_err(|violation| {
                SubmitError::Batch(BindError::Rejected {
                    blocks: batch.len() as u32,
                    reason: format!("sparse bind check: {violation}"),
                })
            })?;
        }
        let slices: Vec<(vk::Image, &[vk::SparseImageMemoryBind])> =
            entries.iter().map(|(image, e)| (*image, e.as_slice())).collect();
        let opaque: Vec<(vk::Image, &[vk::SparseMemoryBind])> = self
            .images
            .iter()
            .zip(&opaque_per_image)
            .map(|(image, binds)| (image.raw(), binds.as_slice()))
            .collect();
        if self.log.is_some() {
            self.write_log(&bind_log::batch_text(batch, frames.is_some_and(|f| f.value > 0)))
                .map_err(SubmitError::Device)?;
        }
        let mut waits: Vec<(vk::Semaphore, u64)> = Vec::with_capacity(2);
        if self.signalled > 0 {
            waits.push((self.timeline.raw(), self.signalled));
        }
        if let Some(frames) = frames.filter(|f| f.value > 0) {
            waits.push((frames.semaphore, frames.value));
        }
        let started = Instant::now();
        let value = self.signalled + 1;
        submit_bind_sparse_after(
            &self.device,
            &slices,
            &opaque,
            &waits,
            &[],
            Some((self.timeline.raw(), value)),
            vk::Fence::null(),
        )
        .map_err(SubmitError::Device)?;
        self.signalled = value;
        Ok(BindReport {
            blocks: batch.len() as u32,
            entries: entries.iter().map(|(_, e)| e.len() as u32).sum::<u32>()
                + opaque_per_image.iter().map(|binds| binds.len() as u32).sum::<u32>(),
            seconds: started.elapsed().as_secs_f64(),
        })
    }
}

impl SparseBinder for VulkanBinder {
    fn submit(&mut self, batch: &[BindOp]) -> std::result::Result<BindReport, BindError> {
        self.submit_ops(batch, None).map_err(|e| match e {
            SubmitError::Batch(e) => e,
            SubmitError::Device(e) => BindError::Rejected {
                blocks: batch.len() as u32,
                reason: e.to_string(),
            },
        })
    }
}

/// A bind op in Vulkan's terms: a block of a level, or an opaque range (a
/// tail block on a device with a tail).
enum Resolved {
    Block(SparseBlockBind),
    Opaque(vk::SparseMemoryBind),
}

/// Why a batch was not submitted: the batch itself, or the device.
enum SubmitError {
    Batch(BindError),
    Device(EngineError),
}

impl Drop for VulkanBinder {
    fn drop(&mut self) {
        // Chunks must outlive every bind that references them; the device
        // idles before the memory is returned.
        let _ = self.device.wait_idle();
        if let Some(log) = &self.log {
            open_bind_logs().retain(|open| *open != log.key);
        }
    }
}

/// The bind log's text format, one record per line, fields separated by
/// spaces (all numbers decimal):
///
/// ```text
/// citystream-bind-log 2
/// image INDEX WIDTH HEIGHT LAYERS MIPS VK_FORMAT GRANULARITY_W GRANULARITY_H BLOCK_BYTES
///       TAIL_FIRST_LEVEL TAIL_BLOCKS TAIL_SINGLE(0|1)     (one line; no tail: MIPS 0 0)
/// chunk INDEX BYTES
/// batch OPERATIONS WAITS_FOR_FRAMES(0|1)
/// bind IMAGE LAYER LEVEL X Y CHUNK OFFSET      (OPERATIONS lines of bind, unbind,
/// unbind IMAGE LAYER LEVEL X Y                  bind-tail or unbind-tail follow batch)
/// bind-tail IMAGE LAYER INDEX CHUNK OFFSET     (block INDEX of the layer's mip tail; layer 0 when single)
/// unbind-tail IMAGE LAYER INDEX
/// copy IMAGE LAYER LEVEL X Y WIDTH HEIGHT      (texels; recorded after the batches before it)
/// ```
///
/// Version 1 logs (no tail fields, no tail lines) are still read.
pub mod bind_log {
    use citystream_cache::BindOp;

    /// The first line of a bind log of this format.
    pub const HEADER: &str = "citystream-bind-log 2";

    /// The first line of a version 1 log (written before mip tails).
    pub const HEADER_V1: &str = "citystream-bind-log 1";

    /// A batch's lines.
    pub fn batch_text(batch: &[BindOp], waits_for_frames: bool) -> String {
        let mut text = format!("batch {} {}\n", batch.len(), u8::from(waits_for_frames));
        for op in batch {
            let b = op.block();
            match op {
                BindOp::Bind { memory, .. } if b.is_tail() => {
                    text += &format!(
                        "bind-tail {} {} {} {} {}\n",
                        b.image, b.layer, b.x, memory.chunk, memory.offset
                    )
                }
                BindOp::Unbind { .. } if b.is_tail() => {
                    text += &format!("unbind-tail {} {} {}\n", b.image, b.layer, b.x)
                }
                BindOp::Bind { memory, .. } => {
                    text += &format!(
                        "bind {} {} {} {} {} {} {}\n",
                        b.image, b.layer, b.mip, b.x, b.y, memory.chunk, memory.offset
                    )
                }
                BindOp::Unbind { .. } => text += &format!("unbind {} {} {} {} {}\n", b.image, b.layer, b.mip, b.x, b.y),
            }
        }
        text
    }
}

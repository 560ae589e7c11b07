//! `citystream bind-replay LOG`: replays a bind log (`CITYSTREAM_BIND_LOG`,
//! format in `citystream_engine::binder::bind_log`) on this machine's device:
//! the same sparse images, memory chunks, bind batches in the same order and
//! copies into the same blocks (of zeros), with the bind checker on, so what
//! led up to a driver fault can be run again without the city, the camera
//! or the streaming that produced it.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use citystream_cache::{BindOp, BlockKey, MemorySlot};
use citystream_engine::binder::{bind_log, VulkanBinder};
use citystream_engine::buffer::{Buffer, BufferDesc};
use citystream_engine::commands::CommandContext;
use citystream_engine::gpu_allocator::MemoryLocation;
use citystream_engine::instance::{default_synchronization_validation, default_validation, InstanceOptions};
use citystream_engine::sparse::{
    bytes_per_texel_block, make_sampleable, texel_block, SparseImage, SparseImageDesc, SparseMemoryChunk, TexelUpload,
};
use citystream_engine::texture_cache::CACHE_FORMATS;
use citystream_engine::{vk, Device, DeviceOptions};

/// Options of `citystream bind-replay`.
#[derive(Debug, clap::Args)]
pub struct BindReplayArgs {
    /// The bind log a run wrote with `CITYSTREAM_BIND_LOG=FILE`.
    pub log: PathBuf,
    /// Replay without the bind checker (to see what the driver does with a log the checker refuses).
    #[arg(long)]
    pub no_check: bool,
}

/// One record of a bind log.
#[derive(Clone, Debug, PartialEq)]
pub enum Record {
    Image {
        index: u32,
        desc: SparseImageDesc,
        /// The sparse granularity (texels) and block size the logging device reported.
        granularity: (u32, u32),
        block_bytes: u32,
        /// The mip tail the logging device had (version 2 logs): first
        /// level, blocks, single; `None` without a tail or in a version 1 log.
        tail: Option<(u32, u32, bool)>,
    },
    Chunk {
        index: u32,
        bytes: u64,
    },
    Batch(Vec<BindOp>),
    Copy {
        image: u32,
        upload: TexelUpload,
    },
}

/// Parses a bind log; errors name the line.
pub fn parse(text: &str) -> Result<Vec<Record>> {
    let mut lines = text.lines().enumerate().map(|(i, line)| (i + 1, line));
    let version_1 = match lines.next() {
        Some((_, header)) if header.trim() == bind_log::HEADER => false,
        Some((_, header)) if header.trim() == bind_log::HEADER_V1 => true,
        Some((_, header)) => bail!(
            "line 1: {header:?} is not a bind log header ({:?} or {:?})",
            bind_log::HEADER,
            bind_log::HEADER_V1
        ),
        None => bail!("the log is empty"),
    };
    let mut records = Vec::new();
    while let Some((number, line)) = lines.next() {
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some((&kind, fields)) = words.split_first() else {
            continue;
        };
        let expect = |count: usize| -> Result<()> {
            if fields.len() != count {
                bail!("line {number}: `{kind}` takes {count} numbers, found {}", fields.len());
            }
            Ok(())
        };
        match kind {
            "image" => {
                let (head, tail) = if version_1 {
                    expect(9)?;
                    (fields, None)
                } else {
                    expect(12)?;
                    let [first_level, blocks, single] = small_numbers(number, &fields[9..])?;
                    if single > 1 {
                        bail!("line {number}: the tail's single flag is {single}, not 0 or 1");
                    }
                    (&fields[..9], Some((first_level, blocks, single == 1)))
                };
                let [index, width, height, layers, mips, format, gw, gh, block_bytes] = small_numbers(number, head)?;
                let tail = tail.filter(|&(first_level, _, _)| first_level < mips);
                let format = i32::try_from(format).with_context(|| format!("line {number}: format {format}"))?;
                let format = vk::Format::from_raw(format);
                let desc = SparseImageDesc {
                    width,
                    height,
                    layers,
                    mips,
                    format,
                };
                records.push(Record::Image {
                    index,
                    desc,
                    granularity: (gw, gh),
                    block_bytes,
                    tail,
                });
            }
            "chunk" => {
                expect(2)?;
                let [index, bytes] = numbers(number, fields)?;
                records.push(Record::Chunk {
                    index: narrow(number, index)?,
                    bytes,
                });
            }
            "batch" => {
                expect(2)?;
                let [operations, _waits_for_frames] = numbers(number, fields)?;
                let mut ops = Vec::with_capacity(operations.min(1 << 20) as usize);
                for _ in 0..operations {
                    let Some((op_number, op_line)) = lines.next() else {
                        bail!("line {number}: the batch announces {operations} operations; the log ends first");
                    };
                    ops.push(parse_op(op_number, op_line)?);
                }
                records.push(Record::Batch(ops));
            }
            "copy" => {
                expect(7)?;
                let [image, layer, mip, x, y, width, height] = small_numbers(number, fields)?;
                let upload = TexelUpload {
                    layer,
                    mip,
                    x,
                    y,
                    width,
                    height,
                    buffer_offset: 0,
                };
                records.push(Record::Copy { image, upload });
            }
            other => bail!("line {number}: unknown record `{other}`"),
        }
    }
    Ok(records)
}

/// The `N` numbers of line `number`'s `fields` (the caller checked there are `N`).
fn numbers<const N: usize>(number: usize, fields: &[&str]) -> Result<[u64; N]> {
    let values = fields
        .iter()
        .map(|f| {
            f.parse::<u64>()
                .with_context(|| format!("line {number}: {f:?} is not a number"))
        })
        .collect::<Result<Vec<u64>>>()?;
    <[u64; N]>::try_from(values).map_err(|v| anyhow::anyhow!("line {number}: {} numbers, not {N}", v.len()))
}

/// `value` of line `number` as a `u32`.
fn narrow(number: usize, value: u64) -> Result<u32> {
    u32::try_from(value).with_context(|| format!("line {number}: {value} is out of range"))
}

/// [`numbers`], each narrowed to a `u32`.
fn small_numbers<const N: usize>(number: usize, fields: &[&str]) -> Result<[u32; N]> {
    let wide: [u64; N] = numbers(number, fields)?;
    let mut small = [0u32; N];
    for (to, from) in small.iter_mut().zip(wide) {
        *to = narrow(number, from)?;
    }
    Ok(small)
}

fn parse_op(number: usize, line: &str) -> Result<BindOp> {
    let words: Vec<&str> = line.split_whitespace().collect();
    let block = |[image, layer, mip, x, y]: [u32; 5]| BlockKey {
        image,
        layer,
        mip,
        x,
        y,
    };
    match words.as_slice() {
        ["bind", rest @ ..] if rest.len() == 7 => {
            let [chunk, offset] = numbers(number, &rest[5..])?;
            Ok(BindOp::Bind {
                block: block(small_numbers(number, &rest[..5])?),
                memory: MemorySlot {
                    chunk: narrow(number, chunk)?,
                    offset,
                },
            })
        }
        ["unbind", rest @ ..] if rest.len() == 5 => Ok(BindOp::Unbind {
            block: block(small_numbers(number, rest)?),
        }),
        ["bind-tail", rest @ ..] if rest.len() == 5 => {
            let [image, layer, index] = small_numbers(number, &rest[..3])?;
            let [chunk, offset] = numbers(number, &rest[3..])?;
            Ok(BindOp::Bind {
                block: BlockKey::tail(image, layer, index),
                memory: MemorySlot {
                    chunk: narrow(number, chunk)?,
                    offset,
                },
            })
        }
        ["unbind-tail", rest @ ..] if rest.len() == 3 => {
            let [image, layer, index] = small_numbers(number, rest)?;
            Ok(BindOp::Unbind {
                block: BlockKey::tail(image, layer, index),
            })
        }
        _ => bail!(
            "line {number}: {line:?} is not `bind` with 7 numbers, `unbind` with 5, `bind-tail` with 5 or \
             `unbind-tail` with 3"
        ),
    }
}

/// What a replay did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Replayed {
    pub images: u32,
    pub chunks: u32,
    pub batches: u64,
    pub operations: u64,
    pub copies: u64,
}

/// Replays `records` on `device`: images, chunks, each batch submitted and
/// waited for, each run of copies recorded and submitted after the batch it
/// follows.
pub fn replay(device: &Arc<Device>, records: &[Record], check: bool) -> Result<Replayed> {
    let mut done = Replayed::default();
    let mut images = Vec::new();
    let mut index = 0;
    while let Some(Record::Image {
        index: expected,
        desc,
        granularity,
        block_bytes,
        tail,
    }) = records.get(index)
    {
        if *expected as usize != images.len() {
            bail!(
                "image records out of order: image {expected} comes as number {}",
                images.len()
            );
        }
        // Only the cache's formats: their texel blocks size the copies' staging.
        if !CACHE_FORMATS.iter().any(|&(_, format, _)| format == desc.format) {
            bail!(
                "image {expected}: format {:?} is not one the cache binds ({}); bind-replay replays the \
                 cache's logs",
                desc.format,
                CACHE_FORMATS.map(|(_, format, _)| format!("{format:?}")).join(", ")
            );
        }
        let image = SparseImage::new(device, *desc, &format!("replayed image {expected}"))?;
        // Block coordinates and memory offsets mean what the logging device made of them.
        if image.granularity() != *granularity || image.block_size() != u64::from(*block_bytes) {
            bail!(
                "image {expected}: the log was written on a device with {granularity:?} texel blocks of {block_bytes} \
                 bytes; {} has {:?} of {}",
                device.name(),
                image.granularity(),
                image.block_size()
            );
        }
        // Tail blocks mean what the logging device's tail made of them.
        let here = citystream_engine::binder::cache_mip_tail(&image).map(|t| (t.first_level, t.blocks, t.single));
        if here != *tail {
            let describe = |tail: Option<(u32, u32, bool)>| match tail {
                None => "no mip tail".to_owned(),
                Some((first, blocks, single)) => format!(
                    "a {}mip tail from level {first} of {blocks} blocks",
                    if single { "single " } else { "" }
                ),
            };
            bail!(
                "image {expected}: the log was written on a device with {}; {} has {} (on a device without \
                 a tail, {}=LEVEL[,single] gives one)",
                describe(*tail),
                device.name(),
                describe(here),
                citystream_engine::sparse::FORCE_MIP_TAIL_ENV
            );
        }
        images.push(Arc::new(image));
        index += 1;
    }
    let Some(first) = images.first() else {
        bail!("the log names no image");
    };
    let (block_bytes, memory_type_bits) = (first.block_size(), first.memory_type_bits());
    done.images = images.len() as u32;
    let mut binder = VulkanBinder::with_checks(device, images.clone(), check)?;
    let mut commands = CommandContext::new(device, "bind replay")?;
    // Every image starts in the layout the cache keeps it in.
    make_sampleable(&mut commands, &images)?;
    let mut copies: Vec<(u32, TexelUpload)> = Vec::new();
    for record in &records[index..] {
        if !matches!(record, Record::Copy { .. }) && !copies.is_empty() {
            record_copies(device, &mut commands, &binder, &images, &std::mem::take(&mut copies))?;
        }
        match record {
            Record::Image { index, .. } => bail!("image {index} comes after the first chunk, batch or copy"),
            Record::Chunk { index, bytes } => {
                let memory = SparseMemoryChunk::with_requirements(
                    device,
                    block_bytes,
                    memory_type_bits,
                    bytes / block_bytes.max(1),
                    &format!("replayed chunk {index}"),
                )?;
                let added = binder.add_chunk(memory)?;
                if added != *index {
                    bail!("chunk {index} of the log was created as chunk {added}");
                }
                done.chunks += 1;
            }
            Record::Batch(ops) => {
                binder
                    .submit_after(ops, None)
                    .with_context(|| format!("batch {} of the log", done.batches + 1))?;
                // Each batch is waited for, as the cache's batches follow one another.
                binder
                    .wait_for_batches()
                    .with_context(|| format!("waiting for batch {} of the log", done.batches + 1))?;
                done.batches += 1;
                done.operations += ops.len() as u64;
            }
            Record::Copy { image, upload } => {
                binder
                    .check_copy(*image, upload)
                    .with_context(|| format!("copy {} of the log", done.copies + 1))?;
                copies.push((*image, *upload));
                done.copies += 1;
            }
        }
    }
    if !copies.is_empty() {
        record_copies(device, &mut commands, &binder, &images, &copies)?;
    }
    device.wait_idle()?;
    Ok(done)
}

/// Records `copies` (of zeros) after the last batch and waits for them.
fn record_copies(
    device: &Arc<Device>,
    commands: &mut CommandContext,
    binder: &VulkanBinder,
    images: &[Arc<SparseImage>],
    copies: &[(u32, TexelUpload)],
) -> Result<()> {
    let mut offset = 0u64;
    let mut placed: Vec<(u32, TexelUpload)> = Vec::with_capacity(copies.len());
    for &(image, upload) in copies {
        let Some(target) = images.get(image as usize) else {
            bail!("a copy names image {image}; the log has {}", images.len());
        };
        let format = target.desc().format;
        let (bw, bh) = texel_block(format);
        let bytes = u64::from(upload.width.div_ceil(bw))
            * u64::from(upload.height.div_ceil(bh))
            * bytes_per_texel_block(format);
        placed.push((
            image,
            TexelUpload {
                buffer_offset: offset,
                ..upload
            },
        ));
        offset += bytes.next_multiple_of(16);
    }
    let staging = Buffer::new(
        device,
        BufferDesc {
            size: offset.max(16),
            usage: vk::BufferUsageFlags::TRANSFER_SRC,
            location: MemoryLocation::CpuToGpu,
        },
        "bind replay zeros",
    )?;
    let cmd = commands.begin()?;
    for (index, image) in images.iter().enumerate() {
        let uploads: Vec<TexelUpload> = placed
            .iter()
            .filter(|(i, _)| *i as usize == index)
            .map(|(_, u)| *u)
            .collect();
        if uploads.is_empty() {
            continue;
        }
        image.record_layout(
            cmd,
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
        );
        image.record_copies(cmd, staging.raw(), &uploads)?;
        image.record_layout(
            cmd,
            vk::ImageLayout::TRANSFER_DST_OPTIMAL,
            vk::ImageLayout::SHADER_READ_ONLY_OPTIMAL,
        );
    }
    let waits: Vec<_> = (binder.last_signalled() > 0)
        .then(|| binder.wait_for_last_batch(vk::PipelineStageFlags2::COPY))
        .into_iter()
        .collect();
    commands.submit_and_wait(&waits)?;
    Ok(())
}

/// The most bytes of bind log `bind-replay` reads: a flight of an hour binding
/// thousands of blocks a second writes some hundreds of MB.
pub const MAX_LOG_BYTES: u64 = 1 << 30;

/// Reads a bind log: a regular file of at most [`MAX_LOG_BYTES`], refused
/// before reading otherwise (a device or a pipe would be read without end).
fn read_log(path: &std::path::Path) -> Result<String> {
    use std::io::Read;
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let metadata = file.metadata().with_context(|| format!("reading {}", path.display()))?;
    if !metadata.is_file() {
        bail!("{} is not a regular file; a bind log is one", path.display());
    }
    if metadata.len() > MAX_LOG_BYTES {
        bail!(
            "{} holds {} bytes; bind-replay reads logs of at most {MAX_LOG_BYTES}",
            path.display(),
            metadata.len()
        );
    }
    let mut text = String::new();
    file.take(MAX_LOG_BYTES + 1)
        .read_to_string(&mut text)
        .with_context(|| format!("reading {} (a bind log is text)", path.display()))?;
    if text.len() as u64 > MAX_LOG_BYTES {
        bail!("{} grew past {MAX_LOG_BYTES} bytes while it was read", path.display());
    }
    Ok(text)
}

/// A log replayed on this machine's device: what it did and the validation errors it raised.
#[derive(Clone, Copy, Debug)]
pub struct LogReplay {
    /// What was replayed.
    pub done: Replayed,
    /// Seconds the replay took, the device's creation aside.
    pub seconds: f64,
    /// Validation errors the layer reported (the command fails on any).
    pub validation_errors: usize,
}

impl std::fmt::Display for LogReplay {
    /// The line `citystream bind-replay` prints.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "replayed {} images, {} chunks, {} batches ({} block operations) and {} copies in {:.2} s; {} validation errors",
            self.done.images,
            self.done.chunks,
            self.done.batches,
            self.done.operations,
            self.done.copies,
            self.seconds,
            self.validation_errors
        )
    }
}

/// Replays the log `args` names on a device of this machine, the bind checker on unless
/// `--no-check`; the flythrough's tests replay the logs of their flights with it.
pub fn replay_log(args: &BindReplayArgs) -> Result<LogReplay> {
    let text = read_log(&args.log)?;
    let records = parse(&text).with_context(|| format!("reading the bind log {}", args.log.display()))?;
    let device = Arc::new(
        Device::new(&DeviceOptions {
            instance: InstanceOptions {
                validation: default_validation(),
                synchronization: default_synchronization_validation(),
                app_name: "citystream bind-replay".into(),
                extensions: Vec::new(),
            },
            device_name: None,
            presentation: false,
            // A bind log replays sparse binds.
            sparse: citystream_engine::device::SparseMode::On,
            ..Default::default()
        })
        .context("creating the Vulkan device")?,
    );
    let start = Instant::now();
    let done =
        replay(&device, &records, !args.no_check).with_context(|| format!("replaying {}", args.log.display()))?;
    Ok(LogReplay {
        done,
        seconds: start.elapsed().as_secs_f64(),
        validation_errors: device.validation_log().errors().len(),
    })
}

/// Runs `citystream bind-replay`.
pub fn run(args: &BindReplayArgs) -> Result<()> {
    let replayed = replay_log(args)?;
    println!("{replayed}");
    let errors = replayed.validation_errors;
    if errors > 0 {
        bail!("{errors} validation errors during the replay");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_log_parses_into_its_records_and_bad_lines_are_named() {
        let log = format!(
            "{}\nimage 0 1024 1024 4 11 131 256 128 65536 8 1 0\nchunk 0 1048576\nbatch 4 1\nbind 0 1 2 3 4 0 65536\nunbind 0 1 2 3 5\nbind-tail 0 3 0 0 0\nunbind-tail 0 2 0\ncopy 0 1 2 0 0 64 64\n",
            bind_log::HEADER
        );
        let records = parse(&log).expect("a valid log");
        assert_eq!(records.len(), 4);
        assert!(matches!(
            &records[0],
            Record::Image {
                tail: Some((8, 1, false)),
                ..
            }
        ));
        assert!(matches!(&records[2], Record::Batch(ops) if ops.len() == 4
            && ops[2] == BindOp::Bind { block: BlockKey::tail(0, 3, 0), memory: MemorySlot { chunk: 0, offset: 0 } }
            && ops[3] == BindOp::Unbind { block: BlockKey::tail(0, 2, 0) }));
        assert!(matches!(&records[3], Record::Copy { image: 0, upload } if upload.width == 64 && upload.mip == 2));
        // A version 1 log (before mip tails): nine numbers an image, no tail.
        let v1 = format!("{}\nimage 0 1024 1024 4 11 131 256 128 65536\n", bind_log::HEADER_V1);
        let records = parse(&v1).expect("a version 1 log");
        assert!(matches!(&records[0], Record::Image { tail: None, .. }));
        assert!(parse(&format!(
            "{}\nimage 0 1024 1024 4 11 131 256 128 65536 8 1 0\n",
            bind_log::HEADER_V1
        ))
        .is_err());
        assert!(parse(&format!(
            "{}\nimage 0 1024 1024 4 11 131 256 128 65536 8 1 2\n",
            bind_log::HEADER
        ))
        .is_err());
        for (bad, line) in [
            ("batch 3 0\nbind 0 0 0 0 0 0 0\n", "line 2"),
            ("chunk 0\n", "line 2"),
            ("copy 0 1 2 x 0 64 64\n", "line 2"),
            ("frobnicate 1\n", "line 2"),
            ("batch 1 0\nbind 0 0 0\n", "line 3"),
            ("batch 1 0\nbind-tail 0 0 0\n", "line 3"),
        ] {
            let error = parse(&format!("{}\n{bad}", bind_log::HEADER)).expect_err(bad);
            assert!(format!("{error:#}").contains(line), "{bad:?}: {error:#}");
        }
        assert!(parse("not a log\n").is_err());
        assert!(parse("").is_err());
    }
}

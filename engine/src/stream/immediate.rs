//! Loads outside the frame loop: every level a request names, now, waiting
//! for the copies (reference renders and measurements, not the steady state).

use ash::vk;
use citystream_cache::geometry::cacheable_mip_count;
use citystream_streaming::loader::TextureFailure;
use citystream_streaming::residency::planner::PackingPass;
use citystream_streaming::residency::{KeepValue, NeedClass};
use citystream_streaming::source::{texel_format, MipSource};
use citystream_streaming::states::{TextureState, TextureStates};

use super::{chain_and_format, source_failure, TextureStreamer};
use crate::commands::{CommandContext, SemaphoreWait};
use crate::error::{EngineError, Result};
use crate::texture_cache::{CycleReport, ResidentCache, StageOutcome};

impl<S: MipSource + 'static> TextureStreamer<S> {
    /// Loads now, bypassing the policy, every level of each `(texture,
    /// finest level)` from that level up to the coarsest not yet resident,
    /// and waits for the copies: for reference renders and measurements,
    /// not for the steady state. Call between frames, after the last
    /// ended frame was submitted (unbinds wait for it). Returns the textures
    /// the cache had to evict meanwhile. A mip that cannot be read goes through
    /// the loader's failure lifecycle (retried, then its texture given up with
    /// the levels it has: [`failed_textures`](Self::failed_textures)), not an error.
    pub fn load_now(&mut self, requests: &[(u32, u32)], commands: &mut CommandContext) -> Result<Vec<u32>> {
        self.check_between_frames("load_now")?;
        let mips = self.missing_levels(requests)?;
        let report = self.load_mips_now(&mips, commands)?;
        Ok(report.invalidated_textures)
    }

    /// Loads now every level of every texture, coarsest first, and tells the
    /// loader they are resident: a fully resident start, as the texture-array
    /// strategy makes when the city fits its budget (Trapp and Döllner load a
    /// city's textures before drawing it). Call before the first frame. The
    /// report sums the cycles; its `invalidated_textures` are those the cache
    /// had no room for (none when the city fits).
    pub fn load_everything_now(&mut self, commands: &mut CommandContext) -> Result<CycleReport> {
        self.check_between_frames("load_everything_now")?;
        let all: Vec<(u32, u32)> = (0..self.loader.source().texture_count()).map(|t| (t, 0)).collect();
        let mips = self.missing_levels(&all)?;
        let report = self.load_mips_now(&mips, commands)?;
        for texture in 0..self.loader.source().texture_count() {
            let resident = self.cache.resident_levels(texture);
            if resident != 0 {
                let finest = TextureStates::resident_status(Some(resident.trailing_zeros()));
                self.states
                    .settle(texture, finest)
                    .map_err(|e| EngineError::InvalidRequest(e.to_string()))?;
            }
        }
        Ok(report)
    }

    /// The levels `requests` (`(texture, finest level)`) ask for that are not
    /// resident, each texture's coarsest first.
    fn missing_levels(&self, requests: &[(u32, u32)]) -> Result<Vec<(u32, u32)>> {
        let mut mips = Vec::new();
        for &(texture, level) in requests {
            let source = self.loader.source();
            let (chain, format) = chain_and_format(source, texture)?;
            // Sources may store levels below one texel block; the cache holds none of them.
            let levels = chain
                .mip_count
                .min(cacheable_mip_count(&texel_format(format), chain.width, chain.height))
                .max(1);
            let resident = self.cache.resident_levels(texture);
            let level = level.min(levels - 1);
            mips.extend(
                (level..levels)
                    .rev()
                    .filter(|l| resident & (1 << l) == 0)
                    .map(|l| (texture, l)),
            );
        }
        Ok(mips)
    }

    /// Loads exactly the given `(texture, level)` mips now and waits for the
    /// copies (pop-in measurements). Call as [`load_now`](Self::load_now).
    pub fn load_levels_now(&mut self, mips: &[(u32, u32)], commands: &mut CommandContext) -> Result<CycleReport> {
        self.check_between_frames("load_levels_now")?;
        self.load_mips_now(mips, commands)
    }

    fn check_between_frames(&self, call: &str) -> Result<()> {
        if self.in_frame {
            return Err(EngineError::InvalidRequest(format!("{call} called inside a frame")));
        }
        Ok(())
    }

    /// Stages `mips` in order and runs cache cycles until all are copied:
    /// when the budget's freed memory waits for a cycle's unbinds
    /// (`MemoryPending`), that cycle runs first. Evicted textures are
    /// invalidated for the loader; the reports of all cycles are summed.
    fn load_mips_now(&mut self, mips: &[(u32, u32)], commands: &mut CommandContext) -> Result<CycleReport> {
        let mut total = CycleReport::default();
        let mut buffer = Vec::new();
        let mut failed = std::collections::HashSet::new();
        for &(texture, level) in mips {
            let given_up = self.states.get(texture).is_ok_and(|s| s.state == TextureState::Failed);
            if given_up || failed.contains(&texture) {
                // A failed texture is not read again, nor its finer levels after a coarser
                // one failed, as in a cycle.
                continue;
            }
            let source = self.loader.source();
            let (chain, format) = chain_and_format(source, texture)?;
            buffer.resize(source.mip_len(texture, level).map_err(source_failure)? as usize, 0);
            // The failure lifecycle of the cycles: retried, then the texture is given up,
            // keeping the levels it has (counted in `totals` and `load_failures`).
            if self.loader.read_now(texture, level, &mut buffer).is_err() {
                failed.insert(texture);
                continue;
            }
            // A cycle at most for pending memory and one after making room.
            let mut cycles_run = 0;
            loop {
                let staged = match self
                    .cache
                    .stage(texture, format, chain.width, chain.height, level, &buffer)
                {
                    Ok(staged) => staged,
                    // The cache cannot hold this texture at all (a format without an
                    // image, an extent above the layer): its failure, as in a cycle.
                    Err(error) => {
                        self.loader.fail_texture(TextureFailure {
                            texture,
                            level: Some(level),
                            reason: error.to_string(),
                        });
                        failed.insert(texture);
                        break;
                    }
                };
                match staged {
                    StageOutcome::Staged { .. } => {
                        // A cycle per staging ring's worth of bytes: its copies go through
                        // the ring, not through one buffer as large as the whole load.
                        if self.cache.staged_bytes() >= self.cache.staging_capacity() {
                            self.finish_cycle_now(commands, &mut total)?;
                        }
                        break;
                    }
                    // The next stage inserts the texture afresh, in a new ring layer.
                    StageOutcome::EvictedItself if cycles_run < 2 => {
                        cycles_run += 1;
                    }
                    StageOutcome::EvictedItself => {
                        return Err(EngineError::InvalidRequest(format!(
                            "texture {texture} level {level}: the cache's ring evicts the texture's own layer \
                             to make room for it; the cache has too few layers for the budget"
                        )))
                    }
                    StageOutcome::MemoryPending if cycles_run < 2 => {
                        self.finish_cycle_now(commands, &mut total)?;
                        cycles_run += 1;
                    }
                    StageOutcome::MemoryPending => {
                        return Err(EngineError::InvalidRequest(format!(
                            "texture {texture} level {level} does not fit the cache's memory budget even after a cycle"
                        )))
                    }
                    outcome @ (StageOutcome::NoRoom { .. } | StageOutcome::NoLayer { .. }) => {
                        // Asked for explicitly: worth more than anything resident.
                        let load = KeepValue {
                            class: NeedClass::Needed,
                            rank: f64::INFINITY,
                        };
                        let mut pass = PackingPass::new();
                        let room = match outcome {
                            StageOutcome::NoRoom { needed_blocks } => self.make_room(&mut pass, needed_blocks, load)?,
                            StageOutcome::NoLayer { image, .. } => self.free_layer(&mut pass, image, load)?,
                            _ => false,
                        };
                        if !room || cycles_run >= 2 {
                            return Err(EngineError::InvalidRequest(format!(
                                "texture {texture} level {level} does not fit the cache's memory budget or layers"
                            )));
                        }
                        // Freed memory is reusable once the unbinds went out.
                        self.finish_cycle_now(commands, &mut total)?;
                        cycles_run += 1;
                    }
                }
            }
        }
        self.finish_cycle_now(commands, &mut total)?;
        Ok(total)
    }

    fn finish_cycle_now(&mut self, commands: &mut CommandContext, total: &mut CycleReport) -> Result<()> {
        // Frames already submitted may still sample what this cycle evicts.
        let frames_before = (self.begun > 0).then(|| SemaphoreWait {
            semaphore: self.frames.raw(),
            stages: vk::PipelineStageFlags2::ALL_COMMANDS,
            value: self.begun,
        });
        let report = self.cache.finish_cycle_after(commands, frames_before)?;
        for &texture in &report.invalidated_textures {
            let _ = self.states.invalidate(texture);
        }
        total.absorb(report);
        Ok(())
    }
}

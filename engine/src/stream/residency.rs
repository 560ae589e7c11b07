//! What the streamer keeps resident: loaded mips staged in the order the
//! view needs them, room made by the residency planner's drops and layer
//! evictions (`citystream_streaming::residency::planner`), and the budget
//! pressure that gates the loader.

use citystream_streaming::loader::TextureFailure;
use citystream_streaming::residency::planner::{
    admission_threshold, packing_order, Admission, LayerEviction, LevelDrop, PackingPass, RoomStep,
};
use citystream_streaming::residency::KeepValue;
use citystream_streaming::source::MipSource;
use citystream_streaming::states::TextureStates;

use super::{chain_and_format, ResidencyCycle, TextureStreamer};
use crate::error::Result;
use crate::texture_cache::StageOutcome;

impl<S: MipSource + 'static> TextureStreamer<S> {
    /// Whether this frame is over budget, and the gate's threshold for the
    /// loader: while the cache is nearly full of levels the view needs,
    /// loads not denser than the least dense of them would only be refused.
    pub(super) fn update_pressure(&mut self, cycle_ran: bool) -> bool {
        let threshold = admission_threshold(&self.cache, &self.needs);
        self.gate.set_threshold(threshold);
        if threshold <= 0.0 {
            self.gate.clear_refused();
        }
        let over = self.pressure.update(
            self.last_cycle.refused_for_room,
            self.gate.declined(),
            threshold,
            cycle_ran,
        );
        if over {
            self.totals.frames_over_budget += 1;
        }
        over
    }

    /// Drops resident levels worth less than `load`, least worth first
    /// (as `pass` plans), until `needed_blocks` blocks of the budget are
    /// free. Each drop first moves the texture's streaming state back to the
    /// level that stays resident (a texture the loader is working on is
    /// skipped). Returns whether the room was made.
    pub(super) fn make_room(&mut self, pass: &mut PackingPass, needed_blocks: u64, load: KeepValue) -> Result<bool> {
        loop {
            let drop = match pass.next_drop(&self.cache, &self.needs, needed_blocks, load) {
                RoomStep::Made => return Ok(true),
                RoomStep::Refused => return Ok(false),
                RoomStep::Drop(drop) => drop,
            };
            if self.drop_level(drop)? {
                pass.level_dropped(&self.cache, &self.needs, drop);
            }
        }
    }

    /// Carries out `drop`; false if the texture's state or the cache no
    /// longer allows it (nothing changed then).
    fn drop_level(&mut self, drop: LevelDrop) -> Result<bool> {
        let LevelDrop { texture, level, next } = drop;
        let holding = TextureStates::resident_status(Some(level));
        let after = TextureStates::resident_status(next);
        if !self.states.try_transition(texture, holding, after).unwrap_or(false) {
            return Ok(false);
        }
        if self.cache.drop_finest(texture)?.is_none() {
            let _ = self.states.try_transition(texture, after, holding);
            return Ok(false);
        }
        self.totals.dropped_levels += 1;
        self.last_cycle.dropped.push((texture, level));
        Ok(true)
    }

    /// Evicts the live layer worth least among the images of `image`'s
    /// format, if `pass` finds one whose every texture is worth less than
    /// `load`. Its textures are reloaded from their first level when the view
    /// asks again.
    pub(super) fn free_layer(&mut self, pass: &mut PackingPass, image: u32, load: KeepValue) -> Result<bool> {
        let Some(eviction) = pass.next_layer_eviction(&self.cache, &self.needs, image, load) else {
            return Ok(false);
        };
        let LayerEviction { image, layer, .. } = eviction;
        self.cache.evict_layer(image, layer)?;
        self.totals.evicted_layers += 1;
        self.last_cycle.evicted_layers += 1;
        pass.layer_evicted(eviction);
        Ok(true)
    }

    /// [`Eviction::View`] packing: loaded mips go in, densest first; when
    /// the budget is full, levels worth less than the mip are dropped
    /// ([`make_room`](Self::make_room)), and a mip that would displace
    /// only levels worth as much or more is refused: its texture's state
    /// returns to what is resident and the gate keeps the loader from
    /// reading it again while the pressure lasts. Mips whose memory waits
    /// for the next unbind batch are kept for the next frame.
    pub(super) fn stage_by_view(&mut self) -> Result<u32> {
        self.last_cycle = ResidencyCycle::default();
        let mut staged = std::mem::take(&mut self.deferred);
        staged.extend(self.take_loaded());
        let mut refused = 0;
        let mut pass = PackingPass::new();
        for (value, mip) in packing_order(&self.needs, staged) {
            let texture = mip.texture;
            let finest = match pass.admit(&self.cache, texture, mip.level) {
                Admission::AlreadyHeld => continue,
                Admission::Refused { finest } => {
                    refused += 1;
                    let _ = self.states.settle(texture, TextureStates::resident_status(finest));
                    continue;
                }
                Admission::Stage { finest } => finest,
            };
            let source = self.loader.source();
            let (chain, format) = chain_and_format(source, texture)?;
            let mut attempts = 0;
            loop {
                attempts += 1;
                let outcome = self
                    .cache
                    .stage(texture, format, chain.width, chain.height, mip.level, &mip.bytes);
                let room = match outcome {
                    Ok(StageOutcome::Staged { .. }) => {
                        self.last_cycle.staged.push((texture, mip.level));
                        break;
                    }
                    Ok(StageOutcome::MemoryPending) => {
                        self.deferred.push(mip);
                        break;
                    }
                    Ok(StageOutcome::NoRoom { needed_blocks }) if attempts < 4 => {
                        self.make_room(&mut pass, needed_blocks, value)?
                    }
                    Ok(StageOutcome::NoLayer { image, .. }) if attempts < 4 => {
                        self.free_layer(&mut pass, image, value)?
                    }
                    Ok(StageOutcome::NoRoom { .. } | StageOutcome::NoLayer { .. } | StageOutcome::EvictedItself) => {
                        false
                    }
                    // The cache cannot hold this texture at all (a format
                    // without an image, an extent above the layer): loading
                    // it again would fail again.
                    Err(error) => {
                        refused += 1;
                        self.loader.fail_texture(TextureFailure {
                            texture,
                            level: Some(mip.level),
                            reason: error.to_string(),
                        });
                        break;
                    }
                };
                if !room {
                    refused += 1;
                    self.last_cycle.refused_for_room += 1;
                    self.totals.refused_for_room += 1;
                    self.gate.refuse(texture, mip.level);
                    let _ = self.states.settle(texture, TextureStates::resident_status(finest));
                    break;
                }
            }
        }
        Ok(refused)
    }

    /// [`Eviction::Ring`](crate::texture_cache::Eviction::Ring): stages every loaded mip
    /// ([`stage_loaded`](Self::stage_loaded)) and counts the layers the cache's ring reused
    /// or its budget took as evicted; the frame is over budget when the budget took one
    /// (with texture arrays, whose layers are the budget, when the ring reused one).
    /// Returns the mips refused and whether the frame was over budget.
    pub(super) fn stage_by_ring(&mut self) -> Result<(u32, bool)> {
        let before = self.cache.packing().stats();
        let refused = self.stage_loaded()?;
        let after = self.cache.packing().stats();
        let ring = after.ring_evictions - before.ring_evictions;
        // Texture-array layers are the budget itself (each holds its full
        // chain's memory): a layer the ring reuses is one the budget lacked.
        let for_budget = after.budget_evictions - before.budget_evictions
            + if self.cache.backing() == crate::device::TextureBacking::Arrays {
                ring
            } else {
                0
            };
        let evicted = after.budget_evictions - before.budget_evictions + ring;
        self.totals.evicted_layers += evicted;
        self.last_cycle = ResidencyCycle {
            evicted_layers: evicted as u32,
            ..ResidencyCycle::default()
        };
        let over_budget = for_budget > 0;
        self.totals.frames_over_budget += u64::from(over_budget);
        Ok((refused, over_budget))
    }

    /// Moves every loaded mip into the cache. Mips the cache cannot take
    /// now are invalidated in the streaming states so Algorithm 1 loads them
    /// again later; textures it cannot take at all are failed.
    fn stage_loaded(&mut self) -> Result<u32> {
        let mut refused = 0;
        // Loader workers stage in whatever order they finish; packing in a
        // fixed order keeps cache placement, and so runs, reproducible.
        let mut staged = self.take_loaded();
        staged.sort_unstable_by_key(|m| (m.texture, std::cmp::Reverse(m.level)));
        for mip in staged {
            let source = self.loader.source();
            let (chain, format) = chain_and_format(source, mip.texture)?;
            let outcome = self
                .cache
                .stage(mip.texture, format, chain.width, chain.height, mip.level, &mip.bytes);
            match outcome {
                Ok(StageOutcome::Staged { .. }) => {}
                Ok(_) => {
                    refused += 1;
                    let _ = self.states.invalidate(mip.texture);
                }
                Err(error) => {
                    refused += 1;
                    self.loader.fail_texture(TextureFailure {
                        texture: mip.texture,
                        level: Some(mip.level),
                        reason: error.to_string(),
                    });
                }
            }
        }
        Ok(refused)
    }
}

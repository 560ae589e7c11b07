//! The residency planner: what gives way when a load needs room.
//!
//! The GPU cache is seen through [`ResidentCache`] (resident and held
//! levels, level bytes, pending uploads, layer contents, the budget); the
//! planner ranks what it holds with a [`NeedTable`] and answers with
//! actions, a [`LevelDrop`] or a [`LayerEviction`], that the cache carries
//! out before asking again. No Vulkan, so every rule is tested on the CPU
//! with a fake cache (the tests below name the rule they hold):
//!
//! - **Drop order** (`drops_follow_the_need_classes_then_their_rank`):
//!   out-of-view levels first, then levels finer than needed, then needed
//!   ones by density ([`KeepValue::cmp_total`]).
//! - **Finest only** (`only_a_textures_finest_level_is_dropped`): a
//!   texture's chain stays contiguous; after a drop its next level becomes
//!   the candidate.
//! - **Margin** (`a_needed_level_yields_only_to_a_load_twice_as_dense`): a
//!   needed level gives way only to a load [`super::REPLACE_MARGIN`] times
//!   denser; nothing gives way to a load worth no more than itself.
//! - **Enough is enough** (`drops_stop_once_the_room_is_made`).
//! - **Pending stays** (`a_texture_with_a_staged_mip_is_not_dropped`,
//!   `a_layer_with_a_staged_mip_is_not_evicted`,
//!   `blocks_that_cannot_be_freed_now_do_not_set_the_gate`): nothing whose upload is
//!   staged in this cycle is dropped or evicted.
//! - **Stale candidates** (`a_level_of_a_layer_evicted_in_this_pass_is_not_dropped`):
//!   a candidate whose texture lost that level since the ranking (its layer
//!   was evicted for another load) is skipped; dropping it again ended a run
//!   on lavapipe once.
//! - **No reload in the pass that dropped it**
//!   (`a_texture_that_gave_way_in_this_pass_is_not_staged_again`).
//! - **Chains grow one level at a time** (`a_load_that_leaves_a_gap_is_refused`,
//!   `a_held_level_is_not_staged_again`).
//! - **Packing order** (`loads_pack_densest_first_and_coarse_before_fine`).
//! - **Layers** (`a_layer_is_worth_its_most_valuable_texture_at_its_coarsest_level`,
//!   `layers_of_equal_worth_go_oldest_first`, `layers_of_every_image_of_the_format_compete`):
//!   a layer is worth its most valuable texture at that texture's coarsest
//!   resident level, the layer worth least goes, oldest first among equals
//!   (as the ring would), over every image of the format.
//! - **The gate** (`the_gate_stays_open_while_a_sixteenth_is_free_or_freeable`,
//!   `blocks_that_cannot_be_freed_now_do_not_set_the_gate`): the loader is
//!   held back only when less than a sixteenth of the budget is free or could
//!   be freed from levels the view does not need, and then to loads denser
//!   than the least dense needed level that dropping would free (not one
//!   whose blocks other levels share, nor one with a mip staged).
//! - **Pressure** (`a_frame_is_over_budget_while_loads_are_refused_or_declined`).

use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap, HashSet};

use citystream_cache::BudgetUse;

use super::{KeepValue, NeedClass, NeedTable};
use crate::source::StagedMip;

/// What the planner reads of a texture cache. Level sets are bit masks
/// (bit `n`: level `n`, 0 the finest).
pub trait ResidentCache {
    /// Textures with a resident level.
    fn resident_textures(&self) -> impl Iterator<Item = u32> + '_;
    /// Levels of `texture` the shaders may sample.
    fn resident_levels(&self, texture: u32) -> u32;
    /// Resident levels and those staged in the current cycle.
    fn held_levels(&self, texture: u32) -> u32;
    /// Whether `texture` has a level staged in the current cycle.
    fn has_pending(&self, texture: u32) -> bool;
    /// Bytes of `level` of `texture` in the cache (0 if it has no place).
    fn level_bytes(&self, texture: u32, level: u32) -> u64;
    /// Budget blocks dropping `level` of `texture` would free: those no
    /// other level shares.
    fn exclusive_blocks(&self, texture: u32, level: u32) -> u32;
    /// Bound blocks against the budget.
    fn budget_use(&self) -> BudgetUse;
    /// The images holding `image`'s format, `image` among them.
    fn images_sharing_format(&self, image: u32) -> &[u32];
    /// The live layers of `image`, oldest first, with their textures.
    fn layer_textures(&self, image: u32) -> Vec<(u32, Vec<u32>)>;
}

/// Drop the finest resident level of `texture` (`level`); `next` is the
/// level that is then its finest, if any.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelDrop {
    /// The texture.
    pub texture: u32,
    /// Its finest resident level, the one to drop.
    pub level: u32,
    /// The level that stays its finest.
    pub next: Option<u32>,
}

/// Evict live layer `layer` of `image` and every texture placed in it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LayerEviction {
    /// The image.
    pub image: u32,
    /// The layer.
    pub layer: u32,
    /// The textures it holds, reloaded from their first level when the view
    /// asks again.
    pub textures: Vec<u32>,
}

/// The next step towards room for a load.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RoomStep {
    /// The budget has the blocks.
    Made,
    /// Nothing left is worth less than the load.
    Refused,
    /// Carry this out (or skip it if it cannot be), then ask again.
    Drop(LevelDrop),
}

/// Whether a loaded mip goes into the cache. `finest` is the texture's
/// finest held level before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admission {
    /// The level, or a finer one, is already held: nothing to do.
    AlreadyHeld,
    /// It would leave a gap in the chain, or the texture gave way in this
    /// pass: its state goes back to `finest`.
    Refused {
        /// The finest held level.
        finest: Option<u32>,
    },
    /// Stage it, making room if the cache asks for it.
    Stage {
        /// The finest held level.
        finest: Option<u32>,
    },
}

/// A resident level that may be dropped, ordered so that a max-heap pops
/// the least worth first.
#[derive(Clone, Copy, Debug)]
struct Victim {
    value: KeepValue,
    texture: u32,
    level: u32,
}

impl PartialEq for Victim {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Victim {}

impl PartialOrd for Victim {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Victim {
    fn cmp(&self, other: &Self) -> Ordering {
        other
            .value
            .cmp_total(&self.value)
            .then_with(|| other.texture.cmp(&self.texture))
    }
}

/// A live cache layer and what evicting it would give up.
#[derive(Clone, Debug)]
struct LayerVictim {
    worth: KeepValue,
    image: u32,
    layer: u32,
    textures: Vec<u32>,
}

/// Every resident level that may be dropped now (each texture's finest,
/// none with a mip staged in this cycle), least worth on top.
fn build_victims<C: ResidentCache>(cache: &C, needs: &NeedTable) -> BinaryHeap<Victim> {
    cache
        .resident_textures()
        .filter(|&texture| !cache.has_pending(texture))
        .map(|texture| {
            let level = cache.resident_levels(texture).trailing_zeros();
            let bytes = cache.level_bytes(texture, level);
            Victim {
                value: needs.keep_value(texture, level, bytes),
                texture,
                level,
            }
        })
        .collect()
}

/// The live layers of `image` and the other images of its format ranked
/// for eviction, least worth last (so `pop` takes it): a layer is worth its
/// most valuable texture at that texture's coarsest resident level.
fn rank_layers<C: ResidentCache>(cache: &C, needs: &NeedTable, image: u32) -> Vec<LayerVictim> {
    let mut layers: Vec<LayerVictim> = cache
        .images_sharing_format(image)
        .iter()
        .flat_map(|&image| {
            cache
                .layer_textures(image)
                .into_iter()
                .map(move |(layer, textures)| (image, layer, textures))
        })
        .map(|(image, layer, textures)| {
            let mut worth = KeepValue {
                class: NeedClass::OutOfView,
                rank: f64::NEG_INFINITY,
            };
            for &texture in &textures {
                let resident = cache.resident_levels(texture);
                if resident == 0 {
                    continue;
                }
                let coarsest = 31 - resident.leading_zeros();
                let value = needs.keep_value(texture, coarsest, cache.level_bytes(texture, coarsest));
                if worth.cmp_total(&value) == Ordering::Less {
                    worth = value;
                }
            }
            LayerVictim {
                worth,
                image,
                layer,
                textures,
            }
        })
        .collect();
    // Oldest first among equals, as the ring would.
    layers.reverse();
    layers.sort_by(|a, b| b.worth.cmp_total(&a.worth));
    layers
}

/// The admission gate's threshold for the loader: 0 (admit everything)
/// while a sixteenth of the budget is free or could be freed from levels
/// the view does not need (only blocks no other level shares count, since
/// dropping the others frees nothing); else the density of the least dense
/// needed level, which a load must beat to be worth reading.
pub fn admission_threshold<C: ResidentCache>(cache: &C, needs: &NeedTable) -> f64 {
    let used = cache.budget_use();
    let easy_room = used.budget_blocks / 16;
    if used.free_blocks() >= easy_room {
        return 0.0;
    }
    let mut freeable = used.free_blocks();
    let mut victims = build_victims(cache, needs);
    while let Some(victim) = victims.pop() {
        let blocks = u64::from(cache.exclusive_blocks(victim.texture, victim.level));
        if blocks == 0 {
            continue;
        }
        if victim.value.class == NeedClass::Needed {
            return victim.value.rank;
        }
        freeable += blocks;
        if freeable >= easy_room {
            break;
        }
    }
    0.0
}

/// Whether frames are over budget, carried from frame to frame.
#[derive(Clone, Copy, Debug, Default)]
pub struct BudgetPressure {
    over_budget: bool,
    last_declined: u64,
}

impl BudgetPressure {
    /// Whether this frame is over budget: the last packing refused a load for
    /// room (`refused_for_room`), the loader declined a load since the last
    /// frame (`declined` is its running count), or the previous frame was
    /// over budget and, with the gate still closed (`threshold` > 0), no
    /// loading cycle ran (`cycle_ran`) to show otherwise.
    pub fn update(&mut self, refused_for_room: u32, declined: u64, threshold: f64, cycle_ran: bool) -> bool {
        let newly_declined = declined > self.last_declined;
        self.last_declined = declined;
        let over = refused_for_room > 0 || newly_declined || (self.over_budget && threshold > 0.0 && !cycle_ran);
        self.over_budget = over;
        over
    }
}

/// Loaded mips in packing order with what each load is worth: densest
/// first, a texture's coarser levels before its finer ones.
pub fn packing_order(needs: &NeedTable, mips: Vec<StagedMip>) -> Vec<(KeepValue, StagedMip)> {
    let mut ranked: Vec<(KeepValue, StagedMip)> = mips
        .into_iter()
        .map(|mip| (needs.load_value(mip.texture, mip.bytes.len() as u64), mip))
        .collect();
    ranked.sort_by(|(a, x), (b, y)| {
        b.cmp_total(a)
            .then_with(|| x.texture.cmp(&y.texture))
            .then_with(|| y.level.cmp(&x.level))
    });
    ranked
}

/// One packing pass of loaded mips into a cache under view eviction. The
/// level candidates are ranked once, when the first load needs room, and
/// the layers once per image; textures that gave way in the pass are
/// remembered so that none is reloaded in the pass that dropped it.
#[derive(Debug, Default)]
pub struct PackingPass {
    victims: Option<BinaryHeap<Victim>>,
    layers: HashMap<u32, Vec<LayerVictim>>,
    gave_way: HashSet<u32>,
}

impl PackingPass {
    /// A pass with nothing ranked yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Whether `level` of `texture` goes into the cache: only the level
    /// next to the finest held one (or any level of a texture holding none),
    /// and not for a texture that gave way in this pass.
    pub fn admit<C: ResidentCache>(&self, cache: &C, texture: u32, level: u32) -> Admission {
        let held = cache.held_levels(texture);
        let finest = (held != 0).then(|| held.trailing_zeros());
        if finest.is_some_and(|f| level >= f) {
            return Admission::AlreadyHeld;
        }
        let follows = finest.is_none_or(|f| level + 1 == f);
        if !follows || self.gave_way.contains(&texture) {
            return Admission::Refused { finest };
        }
        Admission::Stage { finest }
    }

    /// The next level to drop so that `needed_blocks` blocks of the budget
    /// are free for a load worth `load`: the resident level worth least,
    /// if it yields to the load. Call [`Self::level_dropped`] once it is.
    pub fn next_drop<C: ResidentCache>(
        &mut self,
        cache: &C,
        needs: &NeedTable,
        needed_blocks: u64,
        load: KeepValue,
    ) -> RoomStep {
        let heap = self.victims.get_or_insert_with(|| build_victims(cache, needs));
        loop {
            if cache.budget_use().free_blocks() >= needed_blocks {
                return RoomStep::Made;
            }
            let Some(least) = heap.peek().copied() else {
                return RoomStep::Refused;
            };
            if !least.value.yields_to(&load) {
                return RoomStep::Refused;
            }
            heap.pop();
            let texture = least.texture;
            let held = cache.held_levels(texture);
            // Stale: the level left (its layer was evicted) or a mip was staged since the ranking.
            if held == 0 || held.trailing_zeros() != least.level || cache.has_pending(texture) {
                continue;
            }
            let rest = held & !(1 << least.level);
            return RoomStep::Drop(LevelDrop {
                texture,
                level: least.level,
                next: (rest != 0).then(|| rest.trailing_zeros()),
            });
        }
    }

    /// `drop` was carried out: its texture gave way, and its next level
    /// becomes a candidate.
    pub fn level_dropped<C: ResidentCache>(&mut self, cache: &C, needs: &NeedTable, drop: LevelDrop) {
        self.gave_way.insert(drop.texture);
        if let (Some(level), Some(heap)) = (drop.next, self.victims.as_mut()) {
            let bytes = cache.level_bytes(drop.texture, level);
            heap.push(Victim {
                value: needs.keep_value(drop.texture, level, bytes),
                texture: drop.texture,
                level,
            });
        }
    }

    /// The live layer worth least among the images of `image`'s format, if
    /// every texture in it (at its most valuable, coarsest resident level)
    /// is worth less than `load` and none has a mip staged in this cycle.
    /// Call [`Self::layer_evicted`] once it is evicted.
    pub fn next_layer_eviction<C: ResidentCache>(
        &mut self,
        cache: &C,
        needs: &NeedTable,
        image: u32,
        load: KeepValue,
    ) -> Option<LayerEviction> {
        let layers = self
            .layers
            .entry(image)
            .or_insert_with(|| rank_layers(cache, needs, image));
        while let Some(least) = layers.last() {
            if !least.worth.yields_to(&load) {
                return None;
            }
            let least = layers.pop()?;
            // Textures placed or loaded since the ranking make it stale.
            if least.textures.iter().any(|&t| cache.has_pending(t)) {
                continue;
            }
            return Some(LayerEviction {
                image: least.image,
                layer: least.layer,
                textures: least.textures,
            });
        }
        None
    }

    /// `eviction` was carried out: its textures gave way.
    pub fn layer_evicted(&mut self, eviction: LayerEviction) {
        self.gave_way.extend(eviction.textures);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::records::{rec, MeshMetaData};

    /// A cache of whole textures: each level a number of blocks, every
    /// level exclusive unless listed in `shared`.
    #[derive(Clone, Debug, Default)]
    struct FakeTexture {
        resident: u32,
        pending: u32,
        /// Blocks per level, finest first.
        blocks: Vec<u64>,
        shared: u32,
        /// `(image, layer)`.
        place: (u32, u32),
    }

    const BLOCK: u64 = 65536;

    #[derive(Clone, Debug)]
    struct FakeCache {
        textures: Vec<FakeTexture>,
        budget_blocks: u64,
        /// Per image, the images of its format.
        formats: Vec<Vec<u32>>,
        /// Per image, live layers oldest first.
        layers: Vec<Vec<u32>>,
    }

    impl FakeCache {
        fn new(budget_blocks: u64) -> Self {
            Self {
                textures: Vec::new(),
                budget_blocks,
                formats: vec![vec![0]],
                layers: vec![Vec::new()],
            }
        }

        /// Adds a texture of `levels` levels (level n: 4^(levels-1-n) blocks)
        /// with `resident` levels from the coarsest, placed in `(image, layer)`.
        fn texture(&mut self, levels: u32, resident: u32, place: (u32, u32)) -> u32 {
            let blocks = (0..levels).map(|n| 4u64.pow(levels - 1 - n)).collect();
            let resident = if resident == 0 {
                0
            } else {
                ((1u32 << levels) - 1) & !((1u32 << (levels - resident)) - 1)
            };
            self.textures.push(FakeTexture {
                resident,
                blocks,
                place,
                ..FakeTexture::default()
            });
            let layers = &mut self.layers[place.0 as usize];
            if !layers.contains(&place.1) {
                layers.push(place.1);
            }
            self.textures.len() as u32 - 1
        }

        fn live_blocks(&self) -> u64 {
            self.textures
                .iter()
                .map(|t| {
                    let held = t.resident | t.pending;
                    (0..t.blocks.len())
                        .filter(|&n| held & (1 << n) != 0)
                        .map(|n| t.blocks[n])
                        .sum::<u64>()
                })
                .sum()
        }

        fn drop_finest(&mut self, texture: u32) {
            let t = &mut self.textures[texture as usize];
            t.resident &= t.resident.wrapping_sub(1);
        }

        fn evict(&mut self, eviction: &LayerEviction) {
            for &texture in &eviction.textures {
                self.textures[texture as usize].resident = 0;
            }
            self.layers[eviction.image as usize].retain(|&l| l != eviction.layer);
        }

        /// Evicts the layer the pass picks, as the GPU cache does.
        fn evict_for(&mut self, pass: &mut PackingPass, needs: &NeedTable, image: u32, load: KeepValue) -> Vec<u32> {
            let eviction = pass
                .next_layer_eviction(self, needs, image, load)
                .expect("a layer to evict");
            self.evict(&eviction);
            let textures = eviction.textures.clone();
            pass.layer_evicted(eviction);
            textures
        }

        /// Carries out a pass's drops as the GPU cache does: returns what was
        /// dropped and whether the room was made.
        fn make_room(
            &mut self,
            pass: &mut PackingPass,
            needs: &NeedTable,
            needed_blocks: u64,
            load: KeepValue,
        ) -> (Vec<(u32, u32)>, bool) {
            let mut dropped = Vec::new();
            loop {
                match pass.next_drop(self, needs, needed_blocks, load) {
                    RoomStep::Made => return (dropped, true),
                    RoomStep::Refused => return (dropped, false),
                    RoomStep::Drop(drop) => {
                        self.drop_finest(drop.texture);
                        dropped.push((drop.texture, drop.level));
                        pass.level_dropped(self, needs, drop);
                    }
                }
            }
        }
    }

    impl ResidentCache for FakeCache {
        fn resident_textures(&self) -> impl Iterator<Item = u32> + '_ {
            (0..self.textures.len() as u32).filter(|&t| self.textures[t as usize].resident != 0)
        }
        fn resident_levels(&self, texture: u32) -> u32 {
            self.textures.get(texture as usize).map_or(0, |t| t.resident)
        }
        fn held_levels(&self, texture: u32) -> u32 {
            self.textures
                .get(texture as usize)
                .map_or(0, |t| t.resident | t.pending)
        }
        fn has_pending(&self, texture: u32) -> bool {
            self.textures.get(texture as usize).is_some_and(|t| t.pending != 0)
        }
        fn level_bytes(&self, texture: u32, level: u32) -> u64 {
            self.textures
                .get(texture as usize)
                .and_then(|t| t.blocks.get(level as usize))
                .map_or(0, |b| b * BLOCK)
        }
        fn exclusive_blocks(&self, texture: u32, level: u32) -> u32 {
            let t = &self.textures[texture as usize];
            if t.shared & (1 << level) != 0 {
                0
            } else {
                t.blocks[level as usize] as u32
            }
        }
        fn budget_use(&self) -> BudgetUse {
            BudgetUse {
                live_blocks: self.live_blocks(),
                budget_blocks: self.budget_blocks,
            }
        }
        fn images_sharing_format(&self, image: u32) -> &[u32] {
            &self.formats[image as usize]
        }
        fn layer_textures(&self, image: u32) -> Vec<(u32, Vec<u32>)> {
            self.layers[image as usize]
                .iter()
                .map(|&layer| {
                    let textures = (0..self.textures.len() as u32)
                        .filter(|&t| self.textures[t as usize].place == (image, layer))
                        .collect();
                    (layer, textures)
                })
                .collect()
        }
    }

    /// One read-back listing `(texture, level, weight)`, one mesh per
    /// texture (mesh n = texture n).
    fn observe(needs: &mut NeedTable, texture_count: usize, seen: &[(u32, u32, u32)]) {
        let mesh_textures: Vec<u32> = (0..texture_count as u32).collect();
        let records: Vec<MeshMetaData> = seen
            .iter()
            .map(|&(texture, level, weight)| rec(texture, weight, level))
            .collect();
        needs.observe(&records, &mesh_textures);
    }

    /// A need table after `readbacks`.
    fn needs_after(texture_count: usize, readbacks: &[&[(u32, u32, u32)]]) -> NeedTable {
        let mut needs = NeedTable::new(texture_count);
        for seen in readbacks {
            observe(&mut needs, texture_count, seen);
        }
        needs
    }

    /// Read-backs enough for what only earlier ones listed to be out of view.
    fn long_ago(needs: &mut NeedTable, texture_count: usize, still_seen: &[(u32, u32, u32)]) {
        for _ in 0..NeedTable::RECENT_CYCLES {
            observe(needs, texture_count, still_seen);
        }
    }

    /// `count` one-block textures in a budget of `budget_blocks`, each needed
    /// with weight 100 + its id.
    fn full_of_needed(count: u32, budget_blocks: u64) -> (FakeCache, NeedTable) {
        let mut cache = FakeCache::new(budget_blocks);
        for _ in 0..count {
            cache.texture(1, 1, (0, 0));
        }
        let seen: Vec<(u32, u32, u32)> = (0..count).map(|t| (t, 0, 100 + t)).collect();
        (cache, needs_after(count as usize, &[&seen]))
    }

    fn heavy_load(needs: &NeedTable, texture: u32) -> KeepValue {
        needs.load_value(texture, BLOCK)
    }

    #[test]
    fn drops_follow_the_need_classes_then_their_rank() {
        // Four 1-level textures of one block each, full budget.
        let mut cache = FakeCache::new(4);
        for _ in 0..4 {
            cache.texture(1, 1, (0, 0));
        }
        // 0: seen long ago; 1: needed, light; 2: needed, heavy; 3: never seen.
        let mut needs = needs_after(5, &[&[(0, 0, 500)]]);
        long_ago(&mut needs, 5, &[(1, 0, 10), (2, 0, 1000)]);
        let mut pass = PackingPass::new();
        // A very dense load of texture 4 may displace everything but the heavy one.
        let load = KeepValue {
            class: NeedClass::Needed,
            rank: 1000.0 / BLOCK as f64,
        };
        let (dropped, made) = cache.make_room(&mut pass, &needs, 3, load);
        assert!(made);
        assert_eq!(
            dropped,
            vec![(3, 0), (0, 0), (1, 0)],
            "never seen, seen long ago, then the lightest needed"
        );
        // Finer than needed goes before needed.
        let mut cache = FakeCache::new(5);
        let surplus = cache.texture(2, 2, (0, 0)); // levels 0 (4 blocks) and 1 (1 block)
        let needed = cache.texture(1, 1, (0, 0));
        let needs = needs_after(3, &[&[(surplus, 1, 1_000_000), (needed, 0, 1)]]);
        let mut pass = PackingPass::new();
        let (dropped, _) = cache.make_room(&mut pass, &needs, 1, heavy_load(&needs, 2));
        assert_eq!(
            dropped,
            vec![(surplus, 0)],
            "the finer-than-needed level, however heavy its texture"
        );
    }

    #[test]
    fn only_a_textures_finest_level_is_dropped() {
        let mut cache = FakeCache::new(21);
        let chain = cache.texture(3, 3, (0, 0)); // 16 + 4 + 1 blocks
        let needs = needs_after(2, &[]);
        let mut pass = PackingPass::new();
        let load = heavy_load(&needs, 1);
        let (dropped, made) = cache.make_room(&mut pass, &needs, 21, load);
        assert!(made);
        assert_eq!(
            dropped,
            vec![(chain, 0), (chain, 1), (chain, 2)],
            "finest first, one level at a time"
        );
        // The drop names the level that stays.
        let mut cache = FakeCache::new(5);
        let t = cache.texture(2, 2, (0, 0));
        let mut pass = PackingPass::new();
        let RoomStep::Drop(first) = pass.next_drop(&cache, &needs, 5, load) else {
            panic!("a drop");
        };
        assert_eq!(
            first,
            LevelDrop {
                texture: t,
                level: 0,
                next: Some(1)
            }
        );
    }

    #[test]
    fn a_needed_level_yields_only_to_a_load_twice_as_dense() {
        let mut cache = FakeCache::new(1);
        let resident = cache.texture(1, 1, (0, 0));
        let needs = needs_after(4, &[&[(resident, 0, 100), (1, 0, 190), (2, 0, 201), (3, 0, 100)]]);
        // 1.9x as dense: kept.
        let mut pass = PackingPass::new();
        assert_eq!(
            pass.next_drop(&cache, &needs, 1, heavy_load(&needs, 1)),
            RoomStep::Refused
        );
        // As dense: kept (no drop only to load the same again).
        let mut pass = PackingPass::new();
        assert_eq!(
            pass.next_drop(&cache, &needs, 1, heavy_load(&needs, 3)),
            RoomStep::Refused
        );
        // Just over 2x: given way.
        let mut pass = PackingPass::new();
        assert!(matches!(
            pass.next_drop(&cache, &needs, 1, heavy_load(&needs, 2)),
            RoomStep::Drop(LevelDrop {
                texture: 0,
                level: 0,
                ..
            })
        ));
    }

    #[test]
    fn drops_stop_once_the_room_is_made() {
        let mut cache = FakeCache::new(4);
        for _ in 0..4 {
            cache.texture(1, 1, (0, 0));
        }
        let needs = needs_after(5, &[]);
        let mut pass = PackingPass::new();
        let (dropped, made) = cache.make_room(&mut pass, &needs, 2, heavy_load(&needs, 4));
        assert!(made);
        assert_eq!(dropped.len(), 2, "two blocks needed, two dropped: {dropped:?}");
        // Room already there: nothing dropped.
        let mut pass = PackingPass::new();
        let (dropped, made) = cache.make_room(&mut pass, &needs, 2, heavy_load(&needs, 4));
        assert!(made && dropped.is_empty());
    }

    #[test]
    fn a_texture_with_a_staged_mip_is_not_dropped() {
        let mut cache = FakeCache::new(5);
        let staging = cache.texture(2, 1, (0, 0)); // level 1 resident (1 block), level 0 staged (4)
        cache.textures[staging as usize].pending = 1;
        let needs = needs_after(2, &[]);
        let mut pass = PackingPass::new();
        assert_eq!(
            pass.next_drop(&cache, &needs, 1, heavy_load(&needs, 1)),
            RoomStep::Refused
        );
        // Staged after the ranking: skipped when its turn comes.
        let mut cache = FakeCache::new(2);
        let a = cache.texture(1, 1, (0, 0));
        let b = cache.texture(1, 1, (0, 0));
        let needs = needs_after(3, &[]);
        let mut pass = PackingPass::new();
        let RoomStep::Drop(first) = pass.next_drop(&cache, &needs, 1, heavy_load(&needs, 2)) else {
            panic!("a drop");
        };
        assert_eq!(first.texture, a);
        cache.drop_finest(a);
        pass.level_dropped(&cache, &needs, first);
        cache.textures[b as usize].pending = 1 << 1;
        assert_eq!(
            pass.next_drop(&cache, &needs, 2, heavy_load(&needs, 2)),
            RoomStep::Refused
        );
    }

    #[test]
    fn a_level_of_a_layer_evicted_in_this_pass_is_not_dropped() {
        let mut cache = FakeCache::new(3);
        let a = cache.texture(1, 1, (0, 0));
        let b = cache.texture(1, 1, (0, 1));
        let _c = cache.texture(1, 1, (0, 2));
        let needs = needs_after(4, &[]);
        let load = heavy_load(&needs, 3);
        let mut pass = PackingPass::new();
        // The levels are ranked when a first load asks for room (it has it)...
        let (dropped, made) = cache.make_room(&mut pass, &needs, 0, load);
        assert!(made && dropped.is_empty());
        // ...then a layer goes for another load's place...
        assert_eq!(cache.evict_for(&mut pass, &needs, 0, load), vec![a]);
        // ...and the next room must not drop a level that eviction took.
        let (dropped, made) = cache.make_room(&mut pass, &needs, 2, load);
        assert!(made);
        assert_eq!(dropped, vec![(b, 0)]);
    }

    #[test]
    fn a_texture_that_gave_way_in_this_pass_is_not_staged_again() {
        let mut cache = FakeCache::new(2);
        let b = cache.texture(2, 1, (0, 0)); // level 1 resident
        let a = cache.texture(1, 1, (0, 1));
        let needs = needs_after(3, &[]);
        let load = heavy_load(&needs, 2);
        let mut pass = PackingPass::new();
        assert_eq!(pass.admit(&cache, a, 0), Admission::AlreadyHeld);
        assert_eq!(pass.admit(&cache, b, 0), Admission::Stage { finest: Some(1) });
        // b's layer is evicted, then a's level dropped, for other loads.
        assert_eq!(cache.evict_for(&mut pass, &needs, 0, load), vec![b]);
        let (dropped, made) = cache.make_room(&mut pass, &needs, 2, load);
        assert!(made);
        assert_eq!(dropped, vec![(a, 0)]);
        assert_eq!(pass.admit(&cache, a, 0), Admission::Refused { finest: None });
        assert_eq!(pass.admit(&cache, b, 1), Admission::Refused { finest: None });
        // A new pass stages them again.
        assert_eq!(
            PackingPass::new().admit(&cache, a, 0),
            Admission::Stage { finest: None }
        );
    }

    #[test]
    fn a_load_that_leaves_a_gap_is_refused() {
        let mut cache = FakeCache::new(64);
        let t = cache.texture(4, 1, (0, 0)); // level 3 resident
        let pass = PackingPass::new();
        assert_eq!(pass.admit(&cache, t, 1), Admission::Refused { finest: Some(3) });
        assert_eq!(pass.admit(&cache, t, 2), Admission::Stage { finest: Some(3) });
        // A staged level counts as held.
        cache.textures[t as usize].pending = 1 << 2;
        assert_eq!(pass.admit(&cache, t, 1), Admission::Stage { finest: Some(2) });
    }

    #[test]
    fn a_held_level_is_not_staged_again() {
        let mut cache = FakeCache::new(64);
        let t = cache.texture(4, 2, (0, 0)); // levels 2 and 3
        let pass = PackingPass::new();
        assert_eq!(pass.admit(&cache, t, 3), Admission::AlreadyHeld);
        assert_eq!(pass.admit(&cache, t, 2), Admission::AlreadyHeld);
        assert_eq!(pass.admit(&cache, t, 1), Admission::Stage { finest: Some(2) });
    }

    #[test]
    fn loads_pack_densest_first_and_coarse_before_fine() {
        let needs = needs_after(3, &[&[(0, 0, 100), (1, 0, 100), (2, 0, 400)]]);
        let loaded =
            [(0, 0, 64), (1, 1, 16), (1, 2, 16), (2, 0, 64), (0, 1, 16)].map(|(texture, level, bytes)| StagedMip {
                texture,
                level,
                bytes: vec![0; bytes],
            });
        let order: Vec<(u32, u32)> = packing_order(&needs, loaded.into())
            .into_iter()
            .map(|(_, m)| (m.texture, m.level))
            .collect();
        // Density 400/64 = 6.25 = 100/16; ties by texture, then coarse first.
        assert_eq!(order, vec![(0, 1), (1, 2), (1, 1), (2, 0), (0, 0)]);
    }

    #[test]
    fn a_layer_is_worth_its_most_valuable_texture_at_its_coarsest_level() {
        let mut cache = FakeCache::new(64);
        // Layer 0: one heavy needed texture and one never seen; layer 1: two light ones.
        let heavy = cache.texture(2, 2, (0, 0));
        let _unseen = cache.texture(1, 1, (0, 0));
        let light_a = cache.texture(2, 2, (0, 1));
        let light_b = cache.texture(1, 1, (0, 1));
        let needs = needs_after(5, &[&[(heavy, 0, 1000), (light_a, 0, 10), (light_b, 0, 20)]]);
        let mut pass = PackingPass::new();
        let load = KeepValue {
            class: NeedClass::Needed,
            rank: 1e9,
        };
        let first = pass.next_layer_eviction(&cache, &needs, 0, load).expect("a layer");
        assert_eq!(first.layer, 1, "the light layer goes first");
        let second = pass.next_layer_eviction(&cache, &needs, 0, load).expect("another");
        assert_eq!(second.layer, 0);
        // Worth is taken at the coarsest level (1 block): a load 2.5 times as dense
        // as the heavy texture's finest level (4 blocks), but not twice as dense as
        // its coarsest, does not displace it.
        let mut pass = PackingPass::new();
        let modest = KeepValue {
            class: NeedClass::Needed,
            rank: 2.5 * 1000.0 / (4 * BLOCK) as f64,
        };
        let only = pass
            .next_layer_eviction(&cache, &needs, 0, modest)
            .expect("the light layer");
        assert_eq!(only.layer, 1);
        assert_eq!(pass.next_layer_eviction(&cache, &needs, 0, modest), None);
    }

    #[test]
    fn layers_of_equal_worth_go_oldest_first() {
        let mut cache = FakeCache::new(64);
        for layer in [5, 2, 9] {
            cache.texture(1, 1, (0, layer));
        }
        let needs = needs_after(3, &[]);
        let mut pass = PackingPass::new();
        let load = heavy_load(&needs, 0);
        let order: Vec<u32> = std::iter::from_fn(|| pass.next_layer_eviction(&cache, &needs, 0, load))
            .map(|e| e.layer)
            .collect();
        assert_eq!(order, vec![5, 2, 9], "ring order: the order the cache lists them");
    }

    #[test]
    fn a_layer_with_a_staged_mip_is_not_evicted() {
        let mut cache = FakeCache::new(64);
        let staged = cache.texture(2, 1, (0, 0));
        let _other = cache.texture(1, 1, (0, 1));
        cache.textures[staged as usize].pending = 1;
        let needs = needs_after(3, &[]);
        let mut pass = PackingPass::new();
        let load = heavy_load(&needs, 2);
        assert_eq!(
            pass.next_layer_eviction(&cache, &needs, 0, load).map(|e| e.layer),
            Some(1)
        );
        assert_eq!(pass.next_layer_eviction(&cache, &needs, 0, load), None);
    }

    #[test]
    fn layers_of_every_image_of_the_format_compete() {
        let mut cache = FakeCache::new(64);
        cache.formats = vec![vec![0, 1], vec![0, 1], vec![2]];
        cache.layers = vec![Vec::new(), Vec::new(), Vec::new()];
        let kept = cache.texture(1, 1, (0, 0));
        let cheap = cache.texture(1, 1, (1, 0));
        let _other_format = cache.texture(1, 1, (2, 0));
        let needs = needs_after(4, &[&[(kept, 0, 1000)]]);
        let mut pass = PackingPass::new();
        let load = heavy_load(&needs, 3);
        let first = pass.next_layer_eviction(&cache, &needs, 0, load).expect("a layer");
        assert_eq!((first.image, first.textures.clone()), (1, vec![cheap]));
        assert_eq!(
            pass.next_layer_eviction(&cache, &needs, 0, load),
            None,
            "image 2 is another format"
        );
    }

    #[test]
    fn the_gate_stays_open_while_a_sixteenth_is_free_or_freeable() {
        // 32 blocks, 30 live: 2 free = a sixteenth.
        let (cache, needs) = full_of_needed(30, 32);
        assert_eq!(admission_threshold(&cache, &needs), 0.0);
        // 31 live, all needed: the gate closes at the least dense.
        let (cache, needs) = full_of_needed(31, 32);
        assert_eq!(admission_threshold(&cache, &needs), 100.0 / BLOCK as f64);
        // One of them out of view: 1 free + 1 freeable make the sixteenth.
        let seen: Vec<(u32, u32, u32)> = (1..31).map(|t| (t, 0, 100 + t)).collect();
        let needs = needs_after(31, &[&seen]);
        assert_eq!(admission_threshold(&cache, &needs), 0.0);
    }

    #[test]
    fn blocks_that_cannot_be_freed_now_do_not_set_the_gate() {
        let (mut cache, needs) = full_of_needed(31, 32);
        assert_eq!(admission_threshold(&cache, &needs), 100.0 / BLOCK as f64);
        // Texture 0 shares its blocks: dropping it frees nothing, so its density
        // does not set the threshold.
        cache.textures[0].shared = 1;
        assert_eq!(admission_threshold(&cache, &needs), 101.0 / BLOCK as f64);
        // Texture 1 has a mip staged in this cycle: it cannot be dropped now.
        cache.textures[1].pending = 1 << 1;
        assert_eq!(admission_threshold(&cache, &needs), 102.0 / BLOCK as f64);
    }

    #[test]
    fn a_frame_is_over_budget_while_loads_are_refused_or_declined() {
        let mut pressure = BudgetPressure::default();
        assert!(!pressure.update(0, 0, 0.0, true));
        assert!(pressure.update(2, 0, 0.0, true), "a load refused for room");
        assert!(pressure.update(0, 3, 0.5, true), "a load declined since the last frame");
        assert!(
            !pressure.update(0, 3, 0.5, true),
            "the count did not grow and a cycle ran"
        );
        assert!(pressure.update(0, 4, 0.5, false));
        assert!(
            pressure.update(0, 4, 0.5, false),
            "no cycle ran to show the pressure eased"
        );
        assert!(!pressure.update(0, 4, 0.0, false), "the gate opened");
        assert!(pressure.update(0, 5, f64::NAN, false));
        assert!(
            !pressure.update(0, 5, f64::NAN, false),
            "a NaN threshold is an open gate"
        );
    }
}

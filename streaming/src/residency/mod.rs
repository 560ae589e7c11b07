//! What to keep when the view needs more than the memory budget holds.
//!
//! The paper's cache (§3.6) frees memory by reusing whole layers in ring
//! order, whatever the view shows. On a city far larger than its budget that
//! evicts textures the camera is looking at, which then restart from their
//! coarsest level and are streamed again and again. This module ranks
//! resident levels by what the view needs instead:
//!
//! 1. **Out of view**: textures absent from the last
//!    [`NeedTable::RECENT_CYCLES`] feedback read-backs, the ones seen longest
//!    ago first. (A texture whose weight hovers at the τ cutoff drops out of
//!    single read-backs; counting it out of view at once would drop and
//!    reload it every few frames.)
//! 2. **Finer than needed**: levels finer than the feedback asks for
//!    (the camera moved away), finest first.
//! 3. **Needed**: ranked by *density*, the texture's weight (its screen
//!    importance, Eq. 1–3) per byte of the level. Only a texture's finest
//!    resident level is ever a candidate, so chains stay contiguous, and
//!    coarser levels, four times cheaper per level, are worth more per byte.
//!
//! A load is worth its own density. A resident level is dropped for a load
//! only if it ranks below the load, and a needed level only if the load is
//! [`REPLACE_MARGIN`] times denser: feedback weights jitter from frame to
//! frame by tens of percent, and without the margin two textures of similar
//! worth would displace each other in turn. So when the view's needs exceed
//! the budget, the densest set that fits stays resident and the streamer
//! settles: nothing is dropped only to be loaded again.
//!
//! [`AdmissionGate`] carries the lowest density still resident to the
//! loader, which then skips reads the cache would refuse.
//!
//! [`planner`] applies these rankings to a cache seen through the
//! [`planner::ResidentCache`] trait: which levels to drop and which layers
//! to evict for each load, and how hard the gate closes. It returns actions;
//! the GPU cache carries them out.

use std::cmp::Ordering as CmpOrdering;
use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

use crate::records::MeshMetaData;

pub mod planner;

/// How the cache frees memory when the budget is reached.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Eviction {
    /// The paper's §3.6: the oldest layer is evicted whole, in ring order,
    /// whatever it holds.
    Ring,
    /// Nothing is evicted by the cache itself: the [`planner`] drops the
    /// levels the view needs least, and evicts the layers worth least.
    #[default]
    View,
}

impl Eviction {
    /// The name used on command lines and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Eviction::Ring => "ring",
            Eviction::View => "view",
        }
    }
}

/// Why a resident level is (or is not) a good candidate to drop.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum NeedClass {
    /// Not in the latest feedback.
    OutOfView,
    /// Finer than the latest feedback asks for.
    FinerThanNeeded,
    /// The view samples it.
    Needed,
}

/// The worth of keeping (or loading) one level: compared by class first,
/// then by rank within the class. Lower is dropped first.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeepValue {
    /// The class.
    pub class: NeedClass,
    /// Rank within the class: feedback cycle last seen (out of view),
    /// level (finer than needed), weight per byte (needed).
    pub rank: f64,
}

impl KeepValue {
    /// Total order: class, then rank (NaN ranks lowest, so a broken value
    /// is dropped first and never wins room).
    pub fn cmp_total(&self, other: &Self) -> CmpOrdering {
        self.class.cmp(&other.class).then_with(|| {
            let a = if self.rank.is_nan() {
                f64::NEG_INFINITY
            } else {
                self.rank
            };
            let b = if other.rank.is_nan() {
                f64::NEG_INFINITY
            } else {
                other.rank
            };
            a.total_cmp(&b)
        })
    }

    /// Whether this resident level may be dropped to make room for `load`:
    /// a lower class, or both needed and the load [`REPLACE_MARGIN`] times
    /// denser.
    pub fn yields_to(&self, load: &KeepValue) -> bool {
        if self.class == NeedClass::Needed && load.class == NeedClass::Needed {
            let margined = KeepValue {
                rank: self.rank * REPLACE_MARGIN,
                ..*self
            };
            return margined.cmp_total(load) == CmpOrdering::Less;
        }
        self.cmp_total(load) == CmpOrdering::Less
    }
}

/// How many times denser a load must be than a needed level it displaces.
pub const REPLACE_MARGIN: f64 = 2.0;

/// Weight per byte; zero for an empty or weightless level.
pub fn density(weight: u32, bytes: u64) -> f64 {
    if bytes == 0 {
        return 0.0;
    }
    f64::from(weight) / bytes as f64
}

/// The latest need of one texture.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TextureNeed {
    /// The finest level any of its meshes asked for.
    pub level: u32,
    /// The largest weight of its meshes.
    pub weight: u32,
    /// The feedback cycle that last listed it (0: never).
    pub seen: u64,
}

/// The latest feedback, per texture.
#[derive(Clone, Debug)]
pub struct NeedTable {
    needs: Vec<TextureNeed>,
    cycle: u64,
}

impl NeedTable {
    /// Read-backs a texture stays in view after its last one (half a
    /// second at 60 read-backs per second).
    pub const RECENT_CYCLES: u64 = 30;

    /// A table for `texture_count` textures, none seen.
    pub fn new(texture_count: usize) -> Self {
        Self {
            needs: vec![TextureNeed::default(); texture_count],
            cycle: 0,
        }
    }

    /// Feedback cycles observed so far.
    pub fn cycle(&self) -> u64 {
        self.cycle
    }

    /// Records one feedback read-back: each listed texture's finest level
    /// and heaviest mesh. Records of meshes outside `mesh_textures`, or of
    /// textures outside the table, are ignored (the loader reports them).
    pub fn observe(&mut self, records: &[MeshMetaData], mesh_textures: &[u32]) {
        self.cycle += 1;
        let cycle = self.cycle;
        for record in records {
            let Some(&texture) = mesh_textures.get(record.mesh_id as usize) else {
                continue;
            };
            let Some(need) = self.needs.get_mut(texture as usize) else {
                continue;
            };
            if need.seen == cycle {
                need.level = need.level.min(record.mip_level);
                need.weight = need.weight.max(record.weight);
            } else {
                *need = TextureNeed {
                    level: record.mip_level,
                    weight: record.weight,
                    seen: cycle,
                };
            }
        }
    }

    /// The latest need of `texture`, if any feedback listed it.
    pub fn need(&self, texture: u32) -> Option<TextureNeed> {
        self.needs.get(texture as usize).copied().filter(|n| n.seen > 0)
    }

    /// Whether one of the last [`Self::RECENT_CYCLES`] read-backs listed
    /// `texture`.
    pub fn in_view(&self, texture: u32) -> bool {
        self.need(texture)
            .is_some_and(|n| n.seen + Self::RECENT_CYCLES > self.cycle)
    }

    /// What keeping resident level `level` (`bytes` bytes) of `texture` is
    /// worth.
    pub fn keep_value(&self, texture: u32, level: u32, bytes: u64) -> KeepValue {
        match self.need(texture) {
            Some(need) if self.in_view(texture) => {
                if level < need.level {
                    KeepValue {
                        class: NeedClass::FinerThanNeeded,
                        rank: f64::from(level),
                    }
                } else {
                    KeepValue {
                        class: NeedClass::Needed,
                        rank: density(need.weight, bytes),
                    }
                }
            }
            Some(need) => KeepValue {
                class: NeedClass::OutOfView,
                rank: need.seen as f64,
            },
            None => KeepValue {
                class: NeedClass::OutOfView,
                rank: 0.0,
            },
        }
    }

    /// What loading level `level` (`bytes` bytes) of `texture` is worth: a
    /// needed level, ranked by density (weightless if the feedback never
    /// listed it).
    pub fn load_value(&self, texture: u32, bytes: u64) -> KeepValue {
        let weight = self.need(texture).map_or(0, |n| n.weight);
        KeepValue {
            class: NeedClass::Needed,
            rank: density(weight, bytes),
        }
    }
}

/// The loader's view of the cache under pressure: loads whose density is
/// not above the threshold would only be refused, so they are not read.
/// Written by the render thread after each cycle's packing, read by loader
/// workers.
#[derive(Debug, Default)]
pub struct AdmissionGate {
    /// f64 bits of the threshold; 0.0 admits everything.
    threshold_bits: AtomicU64,
    declined: AtomicU64,
    /// Loads the cache refused for room, not read again while the pressure
    /// lasts.
    refused: Mutex<HashSet<(u32, u32)>>,
}

impl AdmissionGate {
    /// A gate that admits everything.
    pub fn new() -> Self {
        Self::default()
    }

    /// Admit only loads denser than `threshold` (0 or less, or NaN: all).
    pub fn set_threshold(&self, threshold: f64) {
        let threshold = if threshold.is_nan() { 0.0 } else { threshold.max(0.0) };
        self.threshold_bits.store(threshold.to_bits(), Ordering::Release);
    }

    /// The current threshold.
    pub fn threshold(&self) -> f64 {
        f64::from_bits(self.threshold_bits.load(Ordering::Acquire))
    }

    /// Whether a load of `bytes` bytes for a mesh of weight `weight` is
    /// admitted: denser than [`REPLACE_MARGIN`] times the threshold, the
    /// least dense needed level it could displace. A declined load is
    /// counted.
    pub fn admit(&self, weight: u32, bytes: u64) -> bool {
        let threshold = self.threshold();
        if threshold <= 0.0 || density(weight, bytes) > threshold * REPLACE_MARGIN {
            return true;
        }
        self.declined.fetch_add(1, Ordering::Relaxed);
        false
    }

    /// Loads declined so far.
    pub fn declined(&self) -> u64 {
        self.declined.load(Ordering::Relaxed)
    }

    fn refused_set(&self) -> MutexGuard<'_, HashSet<(u32, u32)>> {
        self.refused.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The cache refused `level` of `texture` for room: do not read it again
    /// until [`clear_refused`](Self::clear_refused).
    pub fn refuse(&self, texture: u32, level: u32) {
        self.refused_set().insert((texture, level));
    }

    /// Whether `level` of `texture` was refused since the last clear; a
    /// refused load asked for again is counted as declined.
    pub fn is_refused(&self, texture: u32, level: u32) -> bool {
        let refused = self.refused_set().contains(&(texture, level));
        if refused {
            self.declined.fetch_add(1, Ordering::Relaxed);
        }
        refused
    }

    /// The pressure eased: refused loads may be tried again.
    pub fn clear_refused(&self) {
        self.refused_set().clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::records::rec;

    #[test]
    fn classes_order_out_of_view_then_surplus_then_needed() {
        let mut needs = NeedTable::new(4);
        // Meshes 0 and 1 share texture 0; mesh 2 is texture 1.
        let mesh_textures = [0, 0, 1, 2];
        needs.observe(
            &[rec(0, 500, 3), rec(1, 900, 1), rec(2, 200, 0), rec(3, 50, 0)],
            &mesh_textures,
        );
        needs.observe(&[rec(0, 500, 3), rec(1, 900, 1), rec(2, 200, 0)], &mesh_textures);
        let t0 = needs.need(0).expect("seen");
        assert_eq!((t0.level, t0.weight, t0.seen), (1, 900, 2));
        // Texture 2 left the read-backs just now: still in view for a while.
        assert!(needs.in_view(0) && needs.in_view(2) && !needs.in_view(3));
        for _ in 1..NeedTable::RECENT_CYCLES {
            needs.observe(&[rec(0, 500, 3), rec(1, 900, 1)], &mesh_textures);
        }
        assert!(needs.in_view(0) && !needs.in_view(2));
        let gone = needs.keep_value(2, 0, 1 << 20);
        let never = needs.keep_value(3, 0, 1 << 20);
        let surplus = needs.keep_value(0, 0, 1 << 20);
        let needed = needs.keep_value(0, 1, 1 << 18);
        assert_eq!(gone.class, NeedClass::OutOfView);
        assert!(never.yields_to(&gone), "never seen goes before seen long ago");
        assert!(gone.yields_to(&surplus));
        assert!(surplus.yields_to(&needed));
        // Any load outranks surplus and out-of-view levels, even a weightless one.
        let weightless = needs.load_value(3, 1 << 20);
        assert!(surplus.yields_to(&weightless));
        assert!(!needed.yields_to(&weightless));
    }

    #[test]
    fn density_prefers_coarse_levels_and_heavy_textures() {
        let mut needs = NeedTable::new(2);
        needs.observe(&[rec(0, 1000, 0), rec(1, 100, 0)], &[0, 1]);
        let heavy_fine = needs.keep_value(0, 0, 4 << 20);
        let heavy_coarse = needs.keep_value(0, 1, 1 << 20);
        let light_fine = needs.keep_value(1, 0, 4 << 20);
        assert!(heavy_fine.yields_to(&heavy_coarse));
        assert!(light_fine.yields_to(&heavy_fine));
        // Jitter within the margin displaces nothing.
        let jittered = KeepValue {
            rank: heavy_fine.rank * 1.9,
            ..heavy_fine
        };
        assert!(!heavy_fine.yields_to(&jittered));
        // Equal value never yields: no drop only to load the same again.
        let load = needs.load_value(0, 4 << 20);
        assert!(!heavy_fine.yields_to(&load) && !load.yields_to(&heavy_fine));
    }

    #[test]
    fn hard_values() {
        assert_eq!(density(5, 0), 0.0);
        assert_eq!(density(u32::MAX, u64::MAX), f64::from(u32::MAX) / u64::MAX as f64);
        let nan = KeepValue {
            class: NeedClass::Needed,
            rank: f64::NAN,
        };
        let zero = KeepValue {
            class: NeedClass::Needed,
            rank: 0.0,
        };
        assert!(nan.yields_to(&zero), "a NaN rank is dropped first");
        assert!(!zero.yields_to(&nan));
        // Unknown textures and records are ignored, not a panic.
        let mut needs = NeedTable::new(1);
        needs.observe(&[rec(7, 10, 0), rec(0, 10, 0)], &[5]);
        assert_eq!(needs.need(0), None);
        assert_eq!(needs.keep_value(99, 0, 1).class, NeedClass::OutOfView);
    }

    #[test]
    fn gate_declines_loads_not_denser_than_its_threshold() {
        let gate = AdmissionGate::new();
        assert!(gate.admit(0, 1 << 30), "an open gate admits everything");
        gate.set_threshold(0.5);
        assert!(gate.admit(2000, 1000));
        assert!(!gate.admit(1000, 1000), "the margin is not passed");
        assert!(!gate.admit(10, 0));
        assert_eq!(gate.declined(), 2);
        gate.set_threshold(f64::NAN);
        assert_eq!(gate.threshold(), 0.0);
        gate.set_threshold(-3.0);
        assert!(gate.admit(1, 1 << 40));
        gate.refuse(4, 2);
        assert!(gate.is_refused(4, 2) && !gate.is_refused(4, 1));
        assert_eq!(gate.declined(), 3);
        gate.clear_refused();
        assert!(!gate.is_refused(4, 2));
    }
}

//! Per-texture streaming state (paper §3.5, Algorithm 1).
//!
//! Every texture is in one of the states **Initial → Active → Final**, kept
//! in one atomic word together with the mip level it currently has loaded,
//! so that parallel loader workers and the cache can change it without locks:
//!
//! * **Initial**: nothing loaded. The first load is the *smallest useful
//!   mip* ([`MipChain::initial_level`]), after which the texture is Active
//!   (or Final straight away if that level is the base level).
//! * **Active**: level `m` loaded. One streaming cycle loads at most one
//!   more level per texture, `m − 1`, and only while
//!   `sampled mip + b < m` (`b` the mipmap bias). Loading level 0 (the base
//!   level) makes the texture Final.
//! * **Final**: the base level is loaded, or the cache invalidated the
//!   texture (its region was reused). Nothing more is loaded into it.
//!   An invalidated texture is queued; the next streaming cycle's
//!   `UnloadTextures` step tells the sink to make it unsampleable and then
//!   resets it to Initial, because the paper says invalidated textures "will
//!   have to be reloaded in the future".
//! * **Failed** (not in the paper): reading one of its mips failed. It is
//!   never retried, so one bad file cannot stall every cycle; the reason is
//!   counted and kept by the loader.
//!
//! Mip levels: level 0 is the base (finest) level; larger levels are coarser.
//!
//! Threading: [`TextureStates`] is `Sync`; every transition is one
//! compare-and-swap, so racing transitions of one texture resolve to exactly
//! one winner.

use std::sync::atomic::{AtomicU64, Ordering};

/// The extent and mip count of one texture, as the loader needs them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MipChain {
    /// Width of level 0 in texels.
    pub width: u32,
    /// Height of level 0 in texels.
    pub height: u32,
    /// Number of mip levels stored (at least 1).
    pub mip_count: u32,
}

impl MipChain {
    /// Extent of `level`: each side halves per level, never below 1.
    pub fn level_extent(&self, level: u32) -> (u32, u32) {
        let shift = level.min(31);
        ((self.width >> shift).max(1), (self.height >> shift).max(1))
    }

    /// The level streamed first: the finest level whose larger side is at
    /// most 4 texels, i.e. the 4×4 level of a square texture (Algorithm 1,
    /// "we use the 4x4 mipmap"). For block-compressed formats (BC1) this is
    /// the finest level that still fits one 4×4 block, so every coarser
    /// level would cost the same bytes and carry less detail. For a
    /// non-square texture (e.g. 4×32) it is the level where the larger side
    /// reaches 4 (here 1×4, level 3). If the stored chain stops earlier, the
    /// coarsest stored level; textures of 4×4 or smaller start (and end) at
    /// level 0.
    pub fn initial_level(&self) -> u32 {
        let last = self.mip_count.saturating_sub(1);
        let mut level = 0;
        while level < last {
            let (w, h) = self.level_extent(level);
            if w.max(h) <= 4 {
                break;
            }
            level += 1;
        }
        level
    }
}

/// The state of one texture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TextureState {
    /// Nothing loaded yet.
    Initial,
    /// Some level loaded; finer ones may follow.
    Active,
    /// Base level loaded, or invalidated by the cache.
    Final,
    /// A read failed; not retried.
    Failed,
}

/// One texture's state word, unpacked.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TextureStatus {
    /// The state.
    pub state: TextureState,
    /// Finest level loaded (meaningful in Active and base-loaded Final).
    pub mip_level: u32,
    /// Set when the cache invalidated the texture and it awaits unloading.
    pub invalidated: bool,
}

impl TextureStatus {
    /// The state every texture starts in.
    pub const INITIAL: TextureStatus = TextureStatus {
        state: TextureState::Initial,
        mip_level: 0,
        invalidated: false,
    };

    fn pack(self) -> u64 {
        let state = match self.state {
            TextureState::Initial => 0u64,
            TextureState::Active => 1,
            TextureState::Final => 2,
            TextureState::Failed => 3,
        };
        state | (u64::from(self.mip_level) << 8) | (u64::from(self.invalidated) << 40)
    }

    fn unpack(word: u64) -> Self {
        let state = match word & 0b11 {
            0 => TextureState::Initial,
            1 => TextureState::Active,
            2 => TextureState::Final,
            _ => TextureState::Failed,
        };
        TextureStatus {
            state,
            mip_level: ((word >> 8) & 0xFFFF_FFFF) as u32,
            invalidated: (word >> 40) & 1 == 1,
        }
    }
}

/// Algorithm 1's state logic for one texture: which level to load next,
/// and the status after loading it, or `None` if nothing is due.
///
/// `sampled_mip` is the level the GPU metadata asks for, `mip_bias` the
/// controller's `b`; `initial_level` is only evaluated for a texture in the
/// Initial state (it may read the texture's header).
pub fn next_load<E>(
    status: TextureStatus,
    sampled_mip: u32,
    mip_bias: f64,
    initial_level: impl FnOnce() -> Result<u32, E>,
) -> Result<Option<(u32, TextureStatus)>, E> {
    // Loading `level` leaves the texture Active, or Final at level 0.
    let load = |level: u32| {
        let state = if level == 0 {
            TextureState::Final
        } else {
            TextureState::Active
        };
        let status = TextureStatus {
            state,
            mip_level: level,
            invalidated: false,
        };
        (level, status)
    };
    match status.state {
        TextureState::Initial => Ok(Some(load(initial_level()?))),
        TextureState::Active => {
            let current = status.mip_level;
            // NaN bias compares false: nothing loads, which is the safe side.
            let finer_wanted = current > 0 && f64::from(sampled_mip) + mip_bias < f64::from(current);
            Ok(finer_wanted.then(|| load(current - 1)))
        }
        TextureState::Final | TextureState::Failed => Ok(None),
    }
}

/// Error for a texture id outside the table.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("texture {texture} is outside the state table of {len} textures")]
pub struct UnknownTexture {
    /// The id asked for.
    pub texture: u32,
    /// Number of textures in the table.
    pub len: usize,
}

/// The state words of every texture, plus the queue of invalidated ones.
#[derive(Debug)]
pub struct TextureStates {
    words: Box<[AtomicU64]>,
    invalidated: crossbeam::queue::SegQueue<u32>,
}

impl TextureStates {
    /// `count` textures, all Initial.
    pub fn new(count: usize) -> Self {
        let initial = TextureStatus::INITIAL.pack();
        TextureStates {
            words: (0..count).map(|_| AtomicU64::new(initial)).collect(),
            invalidated: crossbeam::queue::SegQueue::new(),
        }
    }

    /// Number of textures.
    pub fn len(&self) -> usize {
        self.words.len()
    }

    /// Whether the table is empty.
    pub fn is_empty(&self) -> bool {
        self.words.is_empty()
    }

    fn word(&self, texture: u32) -> Result<&AtomicU64, UnknownTexture> {
        self.words.get(texture as usize).ok_or(UnknownTexture {
            texture,
            len: self.words.len(),
        })
    }

    /// The current status of `texture`.
    pub fn get(&self, texture: u32) -> Result<TextureStatus, UnknownTexture> {
        Ok(TextureStatus::unpack(self.word(texture)?.load(Ordering::Acquire)))
    }

    /// Move `texture` from `from` to `to` if it is still in `from`; `false`
    /// when another thread changed it first.
    pub fn try_transition(&self, texture: u32, from: TextureStatus, to: TextureStatus) -> Result<bool, UnknownTexture> {
        Ok(self
            .word(texture)?
            .compare_exchange(from.pack(), to.pack(), Ordering::AcqRel, Ordering::Acquire)
            .is_ok())
    }

    /// Sets `texture` to `to` unless it is Failed or awaits unloading
    /// after an invalidation; returns whether it did. The render thread uses
    /// it when the cache holds other levels than the loader planned with (a
    /// level was dropped, or a loaded one refused), so that the next cycle
    /// plans from what is resident.
    pub fn settle(&self, texture: u32, to: TextureStatus) -> Result<bool, UnknownTexture> {
        let word = self.word(texture)?;
        let mut current = word.load(Ordering::Acquire);
        loop {
            let status = TextureStatus::unpack(current);
            if status.invalidated || status.state == TextureState::Failed {
                return Ok(false);
            }
            match word.compare_exchange_weak(current, to.pack(), Ordering::AcqRel, Ordering::Acquire) {
                Ok(_) => return Ok(true),
                Err(actual) => current = actual,
            }
        }
    }

    /// The status of a texture whose finest resident level is `level`
    /// (`None`: nothing resident).
    pub fn resident_status(level: Option<u32>) -> TextureStatus {
        match level {
            None => TextureStatus::INITIAL,
            Some(0) => TextureStatus {
                state: TextureState::Final,
                mip_level: 0,
                invalidated: false,
            },
            Some(level) => TextureStatus {
                state: TextureState::Active,
                mip_level: level,
                invalidated: false,
            },
        }
    }

    /// Mark `texture` failed (whatever its state was).
    pub fn mark_failed(&self, texture: u32) -> Result<(), UnknownTexture> {
        let failed = TextureStatus {
            state: TextureState::Failed,
            mip_level: 0,
            invalidated: false,
        };
        self.word(texture)?.store(failed.pack(), Ordering::Release);
        Ok(())
    }

    /// The cache reused `texture`'s region: make it Final (nothing more is
    /// loaded into the stale region) and queue it for unloading. Returns
    /// `false` if it was already invalidated, never loaded or failed (a
    /// failed texture stays failed: unloading would reset it to Initial and
    /// read it again).
    pub fn invalidate(&self, texture: u32) -> Result<bool, UnknownTexture> {
        let word = self.word(texture)?;
        let mut current = word.load(Ordering::Acquire);
        loop {
            let status = TextureStatus::unpack(current);
            if status.invalidated || matches!(status.state, TextureState::Initial | TextureState::Failed) {
                return Ok(false);
            }
            let to = TextureStatus {
                state: TextureState::Final,
                mip_level: status.mip_level,
                invalidated: true,
            };
            match word.compare_exchange_weak(current, to.pack(), Ordering::AcqRel, Ordering::Acquire) {
                Ok(_) => {
                    self.invalidated.push(texture);
                    return Ok(true);
                }
                Err(actual) => current = actual,
            }
        }
    }

    /// `UnloadTextures` of Algorithm 1: for every texture invalidated since
    /// the last call, run `unload` (make it unsampleable) and then reset it
    /// to Initial. Returns how many were unloaded.
    pub fn unload_invalidated(&self, mut unload: impl FnMut(u32)) -> usize {
        let mut count = 0;
        while let Some(texture) = self.invalidated.pop() {
            if let Ok(word) = self.word(texture) {
                unload(texture);
                word.store(TextureStatus::INITIAL.pack(), Ordering::Release);
                count += 1;
            }
        }
        count
    }

    /// How many textures are in each state: `[initial, active, final, failed]`.
    pub fn census(&self) -> [usize; 4] {
        let mut counts = [0; 4];
        for w in self.words.iter() {
            let i = match TextureStatus::unpack(w.load(Ordering::Relaxed)).state {
                TextureState::Initial => 0,
                TextureState::Active => 1,
                TextureState::Final => 2,
                TextureState::Failed => 3,
            };
            counts[i] += 1;
        }
        counts
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::convert::Infallible;

    fn ok(level: u32) -> impl FnOnce() -> Result<u32, Infallible> {
        move || Ok(level)
    }

    #[test]
    fn initial_level_is_the_4x4_level() {
        let chain = |w, h, n| MipChain {
            width: w,
            height: h,
            mip_count: n,
        };
        // 512 → 256 → 128 → 64 → 32 → 16 → 8 → 4: level 7 of 10.
        assert_eq!(chain(512, 512, 10).initial_level(), 7);
        // 4×32: 4×32, 2×16, 1×8, 1×4 → level 3.
        assert_eq!(chain(4, 32, 6).initial_level(), 3);
        // Chain stored only to level 2: coarsest stored.
        assert_eq!(chain(512, 512, 3).initial_level(), 2);
        assert_eq!(chain(4, 4, 3).initial_level(), 0);
        assert_eq!(chain(2, 1, 2).initial_level(), 0);
        assert_eq!(chain(8, 8, 0).initial_level(), 0);
        assert_eq!(chain(512, 256, 10).level_extent(9), (1, 1));
    }

    #[test]
    fn algorithm1_walk() -> Result<(), Infallible> {
        // Initial → 4×4 level 7, Active.
        let s0 = TextureStatus::INITIAL;
        let (l, s1) = next_load(s0, 2, 0.0, ok(7))?.expect("initial loads");
        assert_eq!((l, s1.state, s1.mip_level), (7, TextureState::Active, 7));
        // Sampled 2, b = 0: 2 + 0 < 7 → load 6.
        let (l, s2) = next_load(s1, 2, 0.0, ok(99))?.expect("refine");
        assert_eq!((l, s2.mip_level), (6, 6));
        // b = 4.5: 2 + 4.5 < 6 is false → nothing.
        assert_eq!(next_load(s2, 2, 4.5, ok(99))?, None);
        // b = 3.5: 5.5 < 6 → load 5.
        assert_eq!(next_load(s2, 2, 3.5, ok(99))?.map(|x| x.0), Some(5));
        // Reaching the sampled level stops: at 2 with sampled 2, 2 < 2 false.
        let at2 = TextureStatus {
            state: TextureState::Active,
            mip_level: 2,
            invalidated: false,
        };
        assert_eq!(next_load(at2, 2, 0.0, ok(99))?, None);
        // Level 1 → 0 makes it Final; Final loads nothing.
        let at1 = TextureStatus { mip_level: 1, ..at2 };
        let (l, fin) = next_load(at1, 0, 0.0, ok(99))?.expect("base");
        assert_eq!((l, fin.state), (0, TextureState::Final));
        assert_eq!(next_load(fin, 0, 0.0, ok(99))?, None);
        // A 4×4 texture goes Initial → Final in one load.
        let (l, s) = next_load(s0, 0, 0.0, ok(0))?.expect("tiny");
        assert_eq!((l, s.state), (0, TextureState::Final));
        // NaN bias never loads a refinement.
        assert_eq!(next_load(s2, 0, f64::NAN, ok(99))?, None);
        Ok(())
    }

    #[test]
    fn header_errors_propagate() {
        let r: Result<_, &str> = next_load(TextureStatus::INITIAL, 0, 0.0, || Err("no file"));
        assert_eq!(r, Err("no file"));
    }

    #[test]
    fn transitions_are_exclusive_and_invalidation_resets() -> Result<(), UnknownTexture> {
        let st = TextureStates::new(3);
        let active = TextureStatus {
            state: TextureState::Active,
            mip_level: 7,
            invalidated: false,
        };
        assert!(st.try_transition(1, TextureStatus::INITIAL, active)?);
        // Second claim from the same observed state loses.
        assert!(!st.try_transition(1, TextureStatus::INITIAL, active)?);
        assert_eq!(st.get(1)?, active);
        assert!(!st.invalidate(0)?, "never loaded: nothing to invalidate");
        assert!(st.invalidate(1)?);
        assert!(!st.invalidate(1)?, "queued once");
        let s = st.get(1)?;
        assert_eq!((s.state, s.invalidated), (TextureState::Final, true));
        let mut unloaded = Vec::new();
        assert_eq!(st.unload_invalidated(|t| unloaded.push(t)), 1);
        assert_eq!(unloaded, vec![1]);
        assert_eq!(st.get(1)?, TextureStatus::INITIAL);
        st.mark_failed(2)?;
        assert_eq!(st.census(), [2, 0, 0, 1]);
        assert_eq!(st.get(3), Err(UnknownTexture { texture: 3, len: 3 }));
        Ok(())
    }

    #[test]
    fn racing_claims_have_one_winner() {
        let st = TextureStates::new(1);
        let to = TextureStatus {
            state: TextureState::Active,
            mip_level: 7,
            invalidated: false,
        };
        let wins: usize = std::thread::scope(|s| {
            let hs: Vec<_> = (0..4)
                .map(|_| s.spawn(|| usize::from(st.try_transition(0, TextureStatus::INITIAL, to).unwrap_or(false))))
                .collect();
            hs.into_iter().map(|h| h.join().unwrap_or(0)).sum()
        });
        assert_eq!(wins, 1);
    }
}

//! Why a texture shows coarser than the view asks: the causes a frame's image error is
//! split by (docs/CONTROLLER.md, "Where the error comes from").
//!
//! Each displayed texel is coarser than the fully resident reference's for one of four
//! reasons, each the lever of one part of the engine:
//!
//! * **Lag** — not requested yet: the feedback the loader last saw does not ask for a
//!   finer level (the view moved since, or the texture came into view since). Prefetch
//!   and a shorter feedback path shrink it.
//! * **Load size** — requested and waiting: the loader knows the level is wanted and has
//!   not bound it yet (the cycle's load size, the block budget, reads in flight). A larger
//!   load size or priority by error per byte shrink it.
//! * **Bias** — the loader knows a finer level is wanted but the controller's mip bias
//!   stops it there (Algorithm 1 loads level `m − 1` only while `sampled + b < m`).
//! * **Budget** — the texture once showed a finer level than now, and the memory budget
//!   dropped or evicted it, or the cache refused the next level for room.
//!
//! The cause is a property of the texture's streaming state, so every texel of one
//! texture carries the same cause; a texture that is not short at all has no error to
//! carry, and the rule still names one cause for it (the one its state reads as), which
//! keeps the four parts a partition of the frame's error.

/// One of the four causes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ShortfallCause {
    /// Not requested yet: the loader's latest feedback does not ask for a finer level.
    Lag,
    /// Requested and waiting for a loading cycle to bind it.
    LoadSize,
    /// Requested, but the mip bias keeps the loader at the level shown.
    Bias,
    /// Finer levels were resident and the budget took them, or the cache refused the
    /// next one for room.
    Budget,
}

impl ShortfallCause {
    /// Every cause, in the order reports list them.
    pub const ALL: [ShortfallCause; 4] = [
        ShortfallCause::Lag,
        ShortfallCause::LoadSize,
        ShortfallCause::Bias,
        ShortfallCause::Budget,
    ];

    /// The name used in `frames.csv` columns (`mse_<name>`) and `summary.json` keys.
    pub fn name(self) -> &'static str {
        match self {
            ShortfallCause::Lag => "lag",
            ShortfallCause::LoadSize => "load",
            ShortfallCause::Bias => "bias",
            ShortfallCause::Budget => "budget",
        }
    }

    /// Index in [`Self::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

/// What the streamer knows of one texture when its frame is measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureShortfall {
    /// The finest level the shaders sample now; `None` while nothing is sampleable.
    pub shown: Option<u32>,
    /// The finest level it was ever sampleable at; `None` if never.
    pub finest_ever: Option<u32>,
    /// The finest level the loader's latest feedback asks for; `None` if no feedback the
    /// loader saw listed it.
    pub requested: Option<u32>,
    /// The next level was refused by the cache for room (the admission gate holds it).
    pub refused_for_room: bool,
    /// The controller's mip bias `b`.
    pub mip_bias: f64,
}

impl TextureShortfall {
    /// The cause this texture's texels carry.
    pub fn cause(&self) -> ShortfallCause {
        let lost_levels = match (self.finest_ever, self.shown) {
            (Some(ever), Some(shown)) => ever < shown,
            (Some(_), None) => true,
            (None, _) => false,
        };
        if lost_levels || self.refused_for_room {
            return ShortfallCause::Budget;
        }
        let Some(requested) = self.requested else {
            return ShortfallCause::Lag;
        };
        match self.shown {
            // The first load ignores the bias (Algorithm 1 always loads the first level).
            None => ShortfallCause::LoadSize,
            Some(shown) if requested < shown => {
                // The loader goes on while sampled + b < current (a NaN bias loads nothing).
                if f64::from(requested) + self.mip_bias < f64::from(shown) {
                    ShortfallCause::LoadSize
                } else {
                    ShortfallCause::Bias
                }
            }
            Some(_) => ShortfallCause::Lag,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(shown: Option<u32>, finest_ever: Option<u32>, requested: Option<u32>, bias: f64) -> TextureShortfall {
        TextureShortfall {
            shown,
            finest_ever,
            requested,
            refused_for_room: false,
            mip_bias: bias,
        }
    }

    #[test]
    fn each_cause_from_the_state_that_means_it() {
        // Never requested: lag, whether something is shown or not.
        assert_eq!(state(None, None, None, 0.0).cause(), ShortfallCause::Lag);
        assert_eq!(state(Some(5), Some(5), None, 0.0).cause(), ShortfallCause::Lag);
        // Requested finer than shown, no bias: waiting for the load size.
        assert_eq!(state(Some(5), Some(5), Some(2), 0.0).cause(), ShortfallCause::LoadSize);
        assert_eq!(state(None, None, Some(2), 3.0).cause(), ShortfallCause::LoadSize);
        // The bias stops the loader: 2 + 3 >= 5.
        assert_eq!(state(Some(5), Some(5), Some(2), 3.0).cause(), ShortfallCause::Bias);
        // 2 + 2.5 < 5: the bias still lets level 4 load.
        assert_eq!(state(Some(5), Some(5), Some(2), 2.5).cause(), ShortfallCause::LoadSize);
        // Once finer than now: the budget took it, whatever the loader knows.
        assert_eq!(state(Some(5), Some(3), Some(2), 0.0).cause(), ShortfallCause::Budget);
        assert_eq!(state(None, Some(3), None, 0.0).cause(), ShortfallCause::Budget);
        let refused = TextureShortfall {
            refused_for_room: true,
            ..state(Some(5), Some(5), Some(2), 0.0)
        };
        assert_eq!(refused.cause(), ShortfallCause::Budget);
        // The loader's feedback asks for no finer level than shown: its knowledge lags.
        assert_eq!(state(Some(2), Some(2), Some(2), 0.0).cause(), ShortfallCause::Lag);
        // A NaN bias loads nothing: the bias, not the load size.
        assert_eq!(state(Some(5), Some(5), Some(2), f64::NAN).cause(), ShortfallCause::Bias);
    }

    #[test]
    fn names_and_indices_follow_the_order() {
        let names: Vec<&str> = ShortfallCause::ALL.iter().map(|c| c.name()).collect();
        assert_eq!(names, ["lag", "load", "bias", "budget"]);
        for (i, cause) in ShortfallCause::ALL.iter().enumerate() {
            assert_eq!(cause.index(), i);
        }
    }
}

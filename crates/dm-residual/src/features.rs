//! The residual's per-particle inputs (method.md §5): post-physics position
//! and velocity, the frame's displacement and H = 3 previous frames of
//! (x, v), positions centred on the cloud's centroid: 9 + 6H = 27 channels.

use crate::ResidualError;

/// Previous frames of (x, v) the residual sees.
pub const HISTORY: usize = 3;
/// Input channels per particle.
pub const CHANNELS: usize = 9 + 6 * HISTORY;

/// Positions and velocities of every particle at one instant.
pub type ParticleState = (Vec<[f64; 3]>, Vec<[f64; 3]>);

/// The state after one frame's substeps, with its history (caller's
/// particle order, SI units).
#[derive(Clone, Debug, PartialEq)]
pub struct FrameInputs {
    /// Positions after the substeps, x̃.
    pub x_tilde: Vec<[f64; 3]>,
    /// Velocities after the substeps, ṽ.
    pub v_tilde: Vec<[f64; 3]>,
    /// Positions at the start of the frame, x_t.
    pub x_start: Vec<[f64; 3]>,
    /// (x, v) at the starts of frames t−1, t−2, t−3, newest first; where
    /// the clip is younger than that, the oldest state repeats.
    pub history: Vec<ParticleState>,
}

impl FrameInputs {
    pub fn particle_count(&self) -> usize {
        self.x_tilde.len()
    }

    /// Checks sizes and finiteness, naming the offending field.
    pub fn validate(&self) -> Result<(), ResidualError> {
        let n = self.x_tilde.len();
        if n == 0 {
            return Err(ResidualError::Input {
                field: "x_tilde".into(),
                problem: "no particles".into(),
            });
        }
        if self.history.len() != HISTORY {
            return Err(ResidualError::Input {
                field: "history".into(),
                problem: format!("{} frames instead of {HISTORY}", self.history.len()),
            });
        }
        let mut fields: Vec<(String, &[[f64; 3]])> = vec![
            ("x_tilde".into(), &self.x_tilde),
            ("v_tilde".into(), &self.v_tilde),
            ("x_start".into(), &self.x_start),
        ];
        for (k, (x, v)) in self.history.iter().enumerate() {
            fields.push((format!("history[{k}].x"), x));
            fields.push((format!("history[{k}].v"), v));
        }
        for (field, values) in fields {
            if values.len() != n {
                return Err(ResidualError::Input {
                    field,
                    problem: format!("{} particles instead of {n}", values.len()),
                });
            }
            if let Some(p) = values.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
                return Err(ResidualError::Input {
                    field,
                    problem: format!("particle {p} is not finite"),
                });
            }
        }
        Ok(())
    }
}

/// The history for frame `t` from the frame-start states `starts[0..=t]`
/// (`starts[t]` is the current frame's start): frames t−1, t−2, t−3,
/// clamped at frame 0.
pub fn history_of<S>(
    starts: &[S],
    t: usize,
    state: impl Fn(&S) -> ParticleState,
) -> Vec<ParticleState> {
    (1..=HISTORY)
        .map(|back| state(&starts[t.saturating_sub(back)]))
        .collect()
}

//! `dm-play`: the interactive playground. A fitted world model
//! runs live in a [`Session`] (the MPM world of `dm-model`, two hands as
//! DCA anchors moved from the keyboard, material and damping set from
//! sliders); [`server`] serves the page and streams the state over a
//! WebSocket; [`record`] writes a session as a new scene bundle;
//! [`encode_frame`] is the binary frame message the page receives.
//!
//! The page (`page/`, embedded) draws splats (or particles) as WebGL point
//! sprites on the client; docs/playground.md has the protocol and the JSON
//! keys, docs/decisions/ (0034–0037) the reasons.

pub mod record;
pub mod scene;
#[cfg(feature = "server")]
pub mod server;
pub mod session;

pub use scene::{SceneView, Sprites, draw_sprites};
#[cfg(feature = "server")]
pub use server::{PageLimits, Playground, serve};
pub use session::{MaterialControl, PlayOptions, Session, SessionState, component_sizes};

use std::path::{Path, PathBuf};

/// Why the playground could not start or a command failed.
#[derive(Debug, thiserror::Error)]
pub enum PlayError {
    #[error(transparent)]
    Bundle(#[from] dm_bundle::BundleError),
    #[error(transparent)]
    Model(#[from] dm_model::ModelError),
    #[error(transparent)]
    Simulation(#[from] dm_mpm::SimError),
    #[error(transparent)]
    Appearance(#[from] dm_appearance::AppearanceError),
    #[error(transparent)]
    Splat(#[from] dm_splat::SplatError),
    #[error("invalid model: {0}")]
    InvalidModel(String),
    #[error("invalid option `{option}`: {problem}")]
    InvalidOption { option: String, problem: String },
    #[error("invalid command: {0}")]
    InvalidCommand(String),
    #[error("{0}")]
    Diverged(String),
    #[error("recording: {0}")]
    Recording(String),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// Opens a fitted model directory (`model.json`, and the splats of
/// `dm-appearance` when present) as a session.
pub fn open_session(model_dir: &Path, options: &PlayOptions) -> Result<Session, PlayError> {
    let model = dm_model::WorldModel::load(&model_dir.join("model.json"))?;
    let mut session = Session::new(model, options)?;
    if dm_appearance::store::has_appearance(model_dir) {
        let (gaussians, _) = dm_appearance::store::load_appearance(model_dir, session.model())?;
        session.attach_splats(gaussians)?;
    }
    Ok(session)
}

/// Magic number at the start of every binary frame message ("DMPF").
pub const FRAME_MAGIC: u32 = u32::from_le_bytes(*b"DMPF");
/// 32-bit words before the sprite positions in a frame message.
pub const FRAME_HEADER_WORDS: usize = 12;

/// The binary WebSocket frame message, little-endian:
/// `magic u32, frame u32, sim_ms f32, hand0 xyz f32, hand1 xyz f32,
/// attached bits u32 (bit k: hand k), hand count u32, sprite count u32`,
/// then the sprite
/// centres as `count × xyz f32`.
pub fn encode_frame(session: &Session) -> Vec<u8> {
    let positions = session.sprite_positions();
    let hands = session.hands();
    let mut out = Vec::with_capacity(4 * (FRAME_HEADER_WORDS + positions.len()));
    out.extend_from_slice(&FRAME_MAGIC.to_le_bytes());
    out.extend_from_slice(&(session.frame() as u32).to_le_bytes());
    out.extend_from_slice(&(session.sim_ms() as f32).to_le_bytes());
    let mut attached = 0u32;
    for (k, h) in hands.iter().enumerate() {
        for c in h.position {
            out.extend_from_slice(&(c as f32).to_le_bytes());
        }
        if h.attached {
            attached |= 1 << k;
        }
    }
    out.extend_from_slice(&attached.to_le_bytes());
    out.extend_from_slice(&(hands.len() as u32).to_le_bytes());
    out.extend_from_slice(&((positions.len() / 3) as u32).to_le_bytes());
    for v in positions {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

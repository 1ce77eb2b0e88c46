//! The playground's HTTP + WebSocket server (axum on tokio). A simulation
//! thread steps the session in real time (never faster than the frame
//! time) and publishes each frame; every connected page receives it as a
//! binary message and sends JSON commands back.
//!
//! Routes: `GET /` (the page), `GET /play.js`, `GET /api/scene` (cameras,
//! sprites, fields: [`SceneMessage`]), `GET /api/state` (the session's
//! [`crate::SessionState`]), `GET /api/components` (connected pieces of the
//! object), `POST /api/command` and `GET /ws` (the same [`Command`]s).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use axum::Json;
use axum::Router;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::{Deserialize, Serialize};
use tokio::sync::watch;

use crate::scene::{PageCamera, Sprites};
use crate::session::{
    DAMPING_RANGE, E_SCALE_RANGE, HAND_COUNT, MaterialControl, NU_RANGE, Session, SessionState,
    component_sizes,
};
use crate::{PlayError, encode_frame, record};

const INDEX_HTML: &str = include_str!("../page/index.html");
const PLAY_JS: &str = include_str!("../page/play.js");

/// A command from the page (`{"type": ...}` JSON; docs/playground.md).
#[derive(Clone, Debug, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Command {
    /// Attach `hand` where the ray first meets the object.
    Grab {
        hand: usize,
        origin: [f64; 3],
        direction: [f64; 3],
    },
    Release {
        hand: usize,
    },
    HandVelocity {
        hand: usize,
        velocity: [f64; 3],
    },
    Material {
        e_scale: f64,
        nu: Option<f64>,
        damping: f64,
    },
    Reset,
    RecordStart,
    /// Stop recording and write the bundle.
    RecordStop,
}

/// The answer to a command.
#[derive(Clone, Debug, Serialize)]
pub struct Reply {
    pub ok: bool,
    pub message: String,
    /// Where a recording was written.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bundle: Option<String>,
}

/// `GET /api/scene`: everything static the page needs.
#[derive(Clone, Debug, Serialize)]
pub struct SceneMessage {
    /// Main view, novel view 1, novel view 2.
    pub cameras: Vec<PageCamera>,
    pub up: [f64; 3],
    pub centre: [f64; 3],
    pub extent: f64,
    pub floor_height: f64,
    pub sprites: Sprites,
    /// Fitted Young's modulus (Pa) of each sprite's particle (before the scale).
    pub sprite_youngs_pa: Vec<f32>,
    /// Dominant expert (0 Neo-Hookean, 1 corotated, 2 St. Venant–Kirchhoff
    /// order of dm-mpm) of each sprite's particle.
    pub sprite_expert: Vec<u8>,
    /// log10 range of the Young's-modulus colour map.
    pub youngs_log10_range: [f64; 2],
    pub e_scale_range: [f64; 2],
    pub nu_range: [f64; 2],
    pub damping_range: [f64; 2],
    /// Fitted median ν (the slider's start).
    pub nu_median: f64,
    pub material: MaterialControl,
    pub frame_dt: f64,
    pub hand_count: usize,
}

/// The running playground: the session, the latest frame, where
/// recordings go.
#[derive(Debug)]
pub struct Playground {
    session: Mutex<Session>,
    frames: watch::Sender<Arc<Vec<u8>>>,
    record_dir: PathBuf,
}

impl Playground {
    /// Starts the simulation thread of `session`; it stops when the
    /// playground is dropped.
    pub fn start(session: Session, record_dir: PathBuf) -> Arc<Self> {
        let first = Arc::new(encode_frame(&session));
        let (frames, _) = watch::channel(first);
        let playground = Arc::new(Self {
            session: Mutex::new(session),
            frames,
            record_dir,
        });
        let weak = Arc::downgrade(&playground);
        std::thread::Builder::new()
            .name("dm-play-sim".into())
            .spawn(move || simulation_loop(weak))
            .ok();
        playground
    }

    /// The session (a poisoned lock is recovered: the session is valid
    /// after every completed call).
    pub fn session(&self) -> MutexGuard<'_, Session> {
        self.session.lock().unwrap_or_else(|e| e.into_inner())
    }

    pub fn state(&self) -> SessionState {
        self.session().state()
    }

    pub fn scene(&self) -> SceneMessage {
        let s = self.session();
        let view = s.view();
        let sprites = s.sprites();
        let youngs = s.fitted_youngs();
        let expert = s.dominant_expert();
        let sprite_youngs_pa: Vec<f32> = sprites
            .particle
            .iter()
            .map(|&p| youngs[p as usize] as f32)
            .collect();
        let sprite_expert = sprites
            .particle
            .iter()
            .map(|&p| expert[p as usize])
            .collect();
        let (lo, hi) = youngs.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &e| {
            (lo.min(e), hi.max(e))
        });
        let (_, nu_median) = s.model().material_medians();
        SceneMessage {
            cameras: view.cameras.iter().map(PageCamera::from).collect(),
            up: view.up,
            centre: view.centre,
            extent: view.extent,
            floor_height: view.floor_height,
            sprites,
            sprite_youngs_pa,
            sprite_expert,
            youngs_log10_range: [lo.log10() - 1.0, hi.log10() + 1.0],
            e_scale_range: E_SCALE_RANGE,
            nu_range: NU_RANGE,
            damping_range: DAMPING_RANGE,
            nu_median,
            material: s.material(),
            frame_dt: s.frame_dt(),
            hand_count: HAND_COUNT,
        }
    }

    /// Runs one command.
    pub fn command(&self, command: Command) -> Result<Reply, PlayError> {
        let done = |message: String| Reply {
            ok: true,
            message,
            bundle: None,
        };
        match command {
            Command::Grab {
                hand,
                origin,
                direction,
            } => {
                let mut s = self.session();
                match s.pick(origin, direction) {
                    Some(p) => {
                        s.grab(hand, p)?;
                        Ok(done(format!("hand {} grabs particle {p}", hand + 1)))
                    }
                    None => Ok(Reply {
                        ok: false,
                        message: "missed the object: click on it".into(),
                        bundle: None,
                    }),
                }
            }
            Command::Release { hand } => {
                self.session().release(hand)?;
                Ok(done(format!("hand {} released", hand + 1)))
            }
            Command::HandVelocity { hand, velocity } => {
                self.session().set_hand_velocity(hand, velocity)?;
                Ok(done(String::new()))
            }
            Command::Material {
                e_scale,
                nu,
                damping,
            } => {
                let mut s = self.session();
                s.set_material(MaterialControl {
                    e_scale,
                    nu,
                    damping,
                })?;
                let m = s.material();
                Ok(done(format!(
                    "E x{:.2}, nu {}, damping {:.1}/s ({} substeps per frame)",
                    m.e_scale,
                    m.nu.map_or("fitted".to_string(), |nu| format!("{nu:.2}")),
                    m.damping,
                    s.state().substeps_per_frame
                )))
            }
            Command::Reset => {
                self.session().reset()?;
                Ok(done("reset to the first frame".into()))
            }
            Command::RecordStart => {
                self.session().start_recording();
                Ok(done("recording".into()))
            }
            Command::RecordStop => {
                let (recording, model, body, view, dt) = {
                    let mut s = self.session();
                    let recording = s
                        .take_recording()
                        .ok_or_else(|| PlayError::Recording("not recording".into()))?;
                    let model = s.model().clone();
                    (
                        recording,
                        model,
                        s.body().clone(),
                        s.view().clone(),
                        s.frame_dt(),
                    )
                };
                let dir = record::write_recording(
                    &self.record_dir,
                    &model,
                    &body,
                    &view,
                    &recording,
                    dt,
                )?;
                Ok(Reply {
                    ok: true,
                    message: format!(
                        "recorded {} frames to {}",
                        recording.positions.len(),
                        dir.display()
                    ),
                    bundle: Some(dir.display().to_string()),
                })
            }
        }
    }

    fn command_reply(&self, command: Command) -> Reply {
        self.command(command).unwrap_or_else(|e| Reply {
            ok: false,
            message: e.to_string(),
            bundle: None,
        })
    }
}

/// Steps the session in real time until the playground is gone.
fn simulation_loop(playground: Weak<Playground>) {
    loop {
        let Some(p) = playground.upgrade() else {
            return;
        };
        let clock = Instant::now();
        let (frame, dt) = {
            let mut s = p.session();
            // A divergence resets the session and is reported in the state.
            let _ = s.step();
            (encode_frame(&s), s.frame_dt())
        };
        p.frames.send_replace(Arc::new(frame));
        drop(p);
        let spare = Duration::from_secs_f64(dt).saturating_sub(clock.elapsed());
        // Always yield a little so commands get the lock between frames.
        std::thread::sleep(spare.max(Duration::from_millis(1)));
    }
}

/// The router of a playground.
pub fn router(playground: Arc<Playground>) -> Router {
    Router::new()
        .route("/", get(index))
        .route("/play.js", get(script))
        .route("/api/scene", get(scene))
        .route("/api/state", get(state))
        .route("/api/components", get(components))
        .route("/api/command", post(command))
        .route("/ws", get(websocket))
        .with_state(playground)
}

/// Serves `playground` on `listener` until the task is dropped.
pub async fn serve(
    listener: tokio::net::TcpListener,
    playground: Arc<Playground>,
) -> std::io::Result<()> {
    axum::serve(listener, router(playground)).await
}

/// Starts a playground server on its own thread and runtime (tests,
/// benchmarks); returns the bound address and the playground.
pub fn spawn_background(
    session: Session,
    addr: SocketAddr,
    record_dir: PathBuf,
) -> Result<(SocketAddr, Arc<Playground>), PlayError> {
    let io = |source| PlayError::Io {
        path: PathBuf::from(addr.to_string()),
        source,
    };
    let listener = std::net::TcpListener::bind(addr).map_err(io)?;
    listener.set_nonblocking(true).map_err(io)?;
    let bound = listener.local_addr().map_err(io)?;
    let playground = Playground::start(session, record_dir);
    let served = playground.clone();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(io)?;
    std::thread::Builder::new()
        .name("dm-play-http".into())
        .spawn(move || {
            runtime.block_on(async move {
                if let Ok(listener) = tokio::net::TcpListener::from_std(listener) {
                    let _ = serve(listener, served).await;
                }
            })
        })
        .map_err(io)?;
    Ok((bound, playground))
}

async fn index() -> Response {
    (
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        INDEX_HTML,
    )
        .into_response()
}

async fn script() -> Response {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        PLAY_JS,
    )
        .into_response()
}

async fn scene(State(p): State<Arc<Playground>>) -> Json<SceneMessage> {
    Json(p.scene())
}

async fn state(State(p): State<Arc<Playground>>) -> Json<SessionState> {
    Json(p.state())
}

/// `{"piece_sizes": [...], "link_m": ...}`: connected components of the
/// particle neighbourhood graph (link 2 × particle spacing), largest first,
/// pieces of fewer than 20 particles left out.
async fn components(State(p): State<Arc<Playground>>) -> Json<serde_json::Value> {
    let (positions, spacing) = {
        let s = p.session();
        (s.positions().to_vec(), s.view().particle_spacing)
    };
    let link = 2.0 * spacing;
    let sizes = component_sizes(&positions, link, 20);
    Json(serde_json::json!({ "piece_sizes": sizes, "link_m": link }))
}

async fn command(
    State(p): State<Arc<Playground>>,
    Json(command): Json<Command>,
) -> (StatusCode, Json<Reply>) {
    let reply = tokio::task::spawn_blocking(move || p.command_reply(command))
        .await
        .unwrap_or_else(|e| Reply {
            ok: false,
            message: e.to_string(),
            bundle: None,
        });
    let status = if reply.ok {
        StatusCode::OK
    } else {
        StatusCode::UNPROCESSABLE_ENTITY
    };
    (status, Json(reply))
}

async fn websocket(State(p): State<Arc<Playground>>, upgrade: WebSocketUpgrade) -> Response {
    upgrade.on_upgrade(move |socket| page_connection(socket, p))
}

/// One page: frames out as they are published, commands in.
async fn page_connection(mut socket: WebSocket, p: Arc<Playground>) {
    let mut frames = p.frames.subscribe();
    loop {
        tokio::select! {
            changed = frames.changed() => {
                if changed.is_err() {
                    return;
                }
                let frame = frames.borrow_and_update().clone();
                if socket.send(Message::Binary(frame.as_ref().clone().into())).await.is_err() {
                    return;
                }
            }
            incoming = socket.recv() => {
                let text = match incoming {
                    Some(Ok(Message::Text(text))) => text,
                    Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                    Some(Ok(_)) => continue,
                };
                let reply = match serde_json::from_str::<Command>(text.as_str()) {
                    Ok(command) => {
                        let p = p.clone();
                        tokio::task::spawn_blocking(move || p.command_reply(command))
                            .await
                            .unwrap_or_else(|e| Reply { ok: false, message: e.to_string(), bundle: None })
                    }
                    Err(e) => Reply { ok: false, message: format!("bad command: {e}"), bundle: None },
                };
                if reply.ok && reply.message.is_empty() {
                    continue;
                }
                let json = serde_json::to_string(&reply).unwrap_or_default();
                if socket.send(Message::Text(json.into())).await.is_err() {
                    return;
                }
            }
        }
    }
}

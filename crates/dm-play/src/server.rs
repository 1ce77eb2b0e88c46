//! The playground's HTTP + WebSocket server (axum on tokio). A simulation
//! thread steps the session in real time (never faster than the frame
//! time) and publishes each frame; every connected page receives it as a
//! binary message and sends JSON commands back.
//!
//! Routes: `GET /` (the page), `GET /play.js`, `GET /api/scene` (cameras,
//! sprites, fields: [`SceneMessage`]), `GET /api/state` (the session's
//! [`crate::SessionState`]), `GET /api/components` (connected pieces of the
//! object), `POST /api/command` and `GET /ws` (the same [`Command`]s).
//!
//! One page cannot cost the others more than [`PageLimits`] allows: a page
//! that sends binary data, oversized or too many commands, keeps sending
//! malformed ones, or stops reading its frames is disconnected, with the
//! reason logged to stderr and sent in the close frame.

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use axum::Json;
use axum::Router;
use axum::body::Bytes;
use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade, close_code};
use axum::extract::{ConnectInfo, DefaultBodyLimit, State};
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

/// What one page may cost the playground. A page over a limit is
/// disconnected (the page limit refuses the connection instead), so no
/// page can hold more than one frame and one message of server memory.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PageLimits {
    /// Pages connected at once; more are refused with 503.
    pub max_pages: usize,
    /// Largest message a page may send, bytes (commands are under 300).
    pub max_message_bytes: usize,
    /// Commands per second a page may send on average (a page sends one
    /// per key change or click)...
    pub commands_per_s: f64,
    /// ...and in one burst.
    pub command_burst: f64,
    /// Malformed commands in a row before the page is disconnected.
    pub max_bad_commands: usize,
    /// How long a frame may wait for a page that does not read it.
    pub send_timeout: Duration,
}

impl Default for PageLimits {
    fn default() -> Self {
        Self {
            max_pages: 32,
            max_message_bytes: 16 * 1024,
            commands_per_s: 100.0,
            command_burst: 200.0,
            max_bad_commands: 16,
            send_timeout: Duration::from_secs(10),
        }
    }
}

/// Disconnection reasons kept for [`Playground::dropped_pages`].
const DROPPED_PAGES_KEPT: usize = 64;

/// The running playground: the session, the latest frame, where
/// recordings go, the pages connected.
#[derive(Debug)]
pub struct Playground {
    session: Mutex<Session>,
    frames: watch::Sender<Bytes>,
    record_dir: PathBuf,
    limits: PageLimits,
    pages: AtomicUsize,
    dropped: Mutex<VecDeque<String>>,
}

impl Playground {
    /// Starts the simulation thread of `session` with the default page
    /// limits; it stops when the playground is dropped.
    pub fn start(session: Session, record_dir: PathBuf) -> Arc<Self> {
        Self::start_with_limits(session, record_dir, PageLimits::default())
    }

    /// [`Playground::start`] with other page limits.
    pub fn start_with_limits(
        session: Session,
        record_dir: PathBuf,
        limits: PageLimits,
    ) -> Arc<Self> {
        let first = Bytes::from(encode_frame(&session));
        let (frames, _) = watch::channel(first);
        let playground = Arc::new(Self {
            session: Mutex::new(session),
            frames,
            record_dir,
            limits,
            pages: AtomicUsize::new(0),
            dropped: Mutex::new(VecDeque::new()),
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

    /// Pages connected now.
    pub fn page_count(&self) -> usize {
        self.pages.load(Ordering::SeqCst)
    }

    /// Why the most recently disconnected misbehaving pages were
    /// disconnected (`ADDRESS: REASON`, oldest first, the last 64).
    pub fn dropped_pages(&self) -> Vec<String> {
        let dropped = self.dropped.lock().unwrap_or_else(|e| e.into_inner());
        dropped.iter().cloned().collect()
    }

    fn log_dropped(&self, page: SocketAddr, reason: &str) {
        let line = format!("{page}: {reason}");
        eprintln!("dm-play: disconnected page {line}");
        let mut dropped = self.dropped.lock().unwrap_or_else(|e| e.into_inner());
        if dropped.len() == DROPPED_PAGES_KEPT {
            dropped.pop_front();
        }
        dropped.push_back(line);
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
        p.frames.send_replace(Bytes::from(frame));
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
        .layer(DefaultBodyLimit::max(playground.limits.max_message_bytes))
        .with_state(playground)
}

/// Serves `playground` on `listener` until the task is dropped.
pub async fn serve(
    listener: tokio::net::TcpListener,
    playground: Arc<Playground>,
) -> std::io::Result<()> {
    axum::serve(
        listener,
        router(playground).into_make_service_with_connect_info::<SocketAddr>(),
    )
    .await
}

/// Starts a playground server on its own thread and runtime (tests,
/// benchmarks); returns the bound address and the playground.
pub fn spawn_background(
    session: Session,
    addr: SocketAddr,
    record_dir: PathBuf,
    limits: PageLimits,
) -> Result<(SocketAddr, Arc<Playground>), PlayError> {
    let io = |source| PlayError::Io {
        path: PathBuf::from(addr.to_string()),
        source,
    };
    let listener = std::net::TcpListener::bind(addr).map_err(io)?;
    listener.set_nonblocking(true).map_err(io)?;
    let bound = listener.local_addr().map_err(io)?;
    let playground = Playground::start_with_limits(session, record_dir, limits);
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

async fn websocket(
    State(p): State<Arc<Playground>>,
    ConnectInfo(page): ConnectInfo<SocketAddr>,
    upgrade: WebSocketUpgrade,
) -> Response {
    let Some(slot) = PageSlot::take(&p) else {
        let message = format!(
            "the playground serves at most {} pages at once",
            p.limits.max_pages
        );
        return (StatusCode::SERVICE_UNAVAILABLE, message).into_response();
    };
    upgrade
        .max_message_size(p.limits.max_message_bytes)
        .max_frame_size(p.limits.max_message_bytes)
        .on_upgrade(move |socket| async move {
            if let Err(reason) = page_connection(socket, &p).await {
                p.log_dropped(page, &reason);
            }
            drop(slot);
        })
}

/// A connected page's place in [`Playground`]'s count, given back on drop.
struct PageSlot(Arc<Playground>);

impl PageSlot {
    fn take(p: &Arc<Playground>) -> Option<Self> {
        let max = p.limits.max_pages;
        p.pages
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()
            .map(|_| Self(p.clone()))
    }
}

impl Drop for PageSlot {
    fn drop(&mut self) {
        self.0.pages.fetch_sub(1, Ordering::SeqCst);
    }
}

/// The commands a page may still send now: refilled at `commands_per_s`
/// up to `command_burst`.
struct CommandBudget {
    tokens: f64,
    refilled: Instant,
}

impl CommandBudget {
    fn new(limits: &PageLimits) -> Self {
        Self {
            tokens: limits.command_burst,
            refilled: Instant::now(),
        }
    }

    fn spend(&mut self, limits: &PageLimits) -> bool {
        let now = Instant::now();
        let refill = limits.commands_per_s * (now - self.refilled).as_secs_f64();
        self.tokens = (self.tokens + refill).min(limits.command_burst);
        self.refilled = now;
        if self.tokens < 1.0 {
            return false;
        }
        self.tokens -= 1.0;
        true
    }
}

/// One page: frames out as they are published, commands in. Returns why a
/// misbehaving page was disconnected (after telling it in a close frame);
/// `Ok` when the page left or the playground stopped.
async fn page_connection(mut socket: WebSocket, p: &Arc<Playground>) -> Result<(), String> {
    let limits = p.limits;
    let mut frames = p.frames.subscribe();
    let mut budget = CommandBudget::new(&limits);
    let mut bad_in_a_row = 0;
    loop {
        tokio::select! {
            changed = frames.changed() => {
                if changed.is_err() {
                    return Ok(());
                }
                // Bytes: every page shares the one encoded frame.
                let frame = frames.borrow_and_update().clone();
                if !send_within(&mut socket, Message::Binary(frame), &limits, "frames").await? {
                    return Ok(());
                }
            }
            incoming = socket.recv() => {
                let text = match incoming {
                    Some(Ok(Message::Text(text))) => text,
                    Some(Ok(Message::Close(_))) | None => return Ok(()),
                    Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                    Some(Ok(Message::Binary(data))) => {
                        let reason = format!(
                            "sent {} bytes of binary data (commands are JSON text)",
                            data.len()
                        );
                        return Err(close(socket, close_code::UNSUPPORTED, reason).await);
                    }
                    // Oversized messages end here: the socket cannot be read on.
                    Some(Err(e)) => return Err(format!("unreadable message: {e}")),
                };
                if !budget.spend(&limits) {
                    let reason = format!(
                        "sent more than {:.0} commands per second",
                        limits.commands_per_s
                    );
                    return Err(close(socket, close_code::POLICY, reason).await);
                }
                let reply = match serde_json::from_str::<Command>(text.as_str()) {
                    Ok(command) => {
                        bad_in_a_row = 0;
                        let p = p.clone();
                        tokio::task::spawn_blocking(move || p.command_reply(command))
                            .await
                            .unwrap_or_else(|e| Reply { ok: false, message: e.to_string(), bundle: None })
                    }
                    Err(e) => {
                        bad_in_a_row += 1;
                        if bad_in_a_row >= limits.max_bad_commands {
                            let reason = format!("sent {bad_in_a_row} malformed commands in a row (last: {e})");
                            return Err(close(socket, close_code::POLICY, reason).await);
                        }
                        Reply { ok: false, message: format!("bad command: {e}"), bundle: None }
                    }
                };
                if reply.ok && reply.message.is_empty() {
                    continue;
                }
                let json = serde_json::to_string(&reply).unwrap_or_default();
                if !send_within(&mut socket, Message::Text(json.into()), &limits, "replies").await? {
                    return Ok(());
                }
            }
        }
    }
}

/// Sends `message` (one of the page's `what`): `Ok(true)` once delivered,
/// `Ok(false)` when the page has gone, the disconnection reason when it
/// did not read for `send_timeout`.
async fn send_within(
    socket: &mut WebSocket,
    message: Message,
    limits: &PageLimits,
    what: &str,
) -> Result<bool, String> {
    match tokio::time::timeout(limits.send_timeout, socket.send(message)).await {
        Ok(sent) => Ok(sent.is_ok()),
        Err(_) => Err(format!(
            "did not read its {what} for {:.1} s",
            limits.send_timeout.as_secs_f64()
        )),
    }
}

/// Tells the page why it is disconnected (best effort: it may not read)
/// and returns the reason. The page's messages still in flight are read
/// and dropped until it answers the close frame (or `CLOSE_DRAIN` passes):
/// a socket dropped with unread data is reset, and a reset discards the
/// close frame before the page can read it.
async fn close(mut socket: WebSocket, code: u16, reason: String) -> String {
    // A close frame's reason holds at most 123 bytes.
    let mut end = reason.len().min(120);
    while !reason.is_char_boundary(end) {
        end -= 1;
    }
    let frame = CloseFrame {
        code,
        reason: reason[..end].into(),
    };
    let _ = tokio::time::timeout(
        Duration::from_secs(1),
        socket.send(Message::Close(Some(frame))),
    )
    .await;
    let _ = tokio::time::timeout(CLOSE_DRAIN, async {
        while let Some(Ok(message)) = socket.recv().await {
            if matches!(message, Message::Close(_)) {
                break;
            }
        }
    })
    .await;
    reason
}

/// How long a disconnected page may take to answer the close frame.
const CLOSE_DRAIN: Duration = Duration::from_secs(2);

//! A foreign-physics scene as a plant: MuJoCo's flex of the scene, stepped
//! a frame at a time by hands the caller moves (dm-plan carries plans out
//! in it). The simulator script runs as a child process that answers one
//! command per line (`mujoco_scene.py --serve`).

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, ChildStdin, ChildStdout, Stdio};

use serde::Deserialize;
use serde_json::json;

use crate::SynthError;
use crate::foreign::{HOLD_RADIUS_M, cannot_start, engine_error, python_in, write_request};
use crate::truth::TruthFile;

/// Positions and velocities (over the last frame) of every truth particle.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantState {
    pub x: Vec<[f32; 3]>,
    pub v: Vec<[f32; 3]>,
}

/// MuJoCo's scene of a foreign truth file, settled with no grip held.
#[derive(Debug)]
pub struct MujocoPlant {
    child: Child,
    input: ChildStdin,
    output: BufReader<ChildStdout>,
    particles: usize,
    hands: usize,
    /// Set when an answer could not be read whole: the stream is out of
    /// step and the child is killed, not asked to stop.
    broken: bool,
    /// Which truth particles are on the surface.
    pub surface: Vec<bool>,
    /// Kept until the child has gone: it holds the script and request.
    _dir: tempfile::TempDir,
}

#[derive(Deserialize)]
struct Answer {
    ok: bool,
    #[serde(default)]
    error: Option<String>,
    #[serde(default)]
    particles: Option<usize>,
}

impl MujocoPlant {
    /// Starts the scene of `truth` (a file dm-synth --engine mujoco wrote)
    /// with `hands` planned hands.
    pub fn start(truth: &TruthFile, hands: usize) -> Result<Self, SynthError> {
        if truth.engine.is_none() {
            return Err(SynthError::InvalidOption {
                option: "engine".into(),
                problem: "the truth file comes from dm-mpm, not MuJoCo".into(),
            });
        }
        let dir = tempfile::Builder::new()
            .prefix("dm-synth-mujoco-plant-")
            .tempdir()
            .map_err(|e| engine_error(format!("creating a temporary directory: {e}")))?;
        let (script, cloud) = write_request(&truth.config, dir.path())?;
        let (python, mut command) = python_in(dir.path());
        let mut child = command
            .arg(&script)
            .arg(dir.path())
            .arg("--serve")
            .arg(hands.to_string())
            .arg(HOLD_RADIUS_M.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| cannot_start(&python, e))?;
        let (Some(input), Some(output)) = (child.stdin.take(), child.stdout.take()) else {
            return Err(engine_error("the simulator's pipes were not opened"));
        };
        let mut plant = Self {
            child,
            input,
            output: BufReader::new(output),
            particles: cloud.len(),
            hands,
            broken: false,
            surface: cloud.on_surface,
            _dir: dir,
        };
        let ready = plant.answer("start")?;
        if ready.particles != Some(plant.particles) {
            return Err(engine_error(format!(
                "the simulator holds {:?} particles, the scene {}",
                ready.particles, plant.particles
            )));
        }
        Ok(plant)
    }

    /// Truth particles.
    pub fn particle_count(&self) -> usize {
        self.particles
    }

    /// The scene's scripted hands from frame `t` to `t + 1`; they grip
    /// their vertices at the first replay.
    pub fn replay(&mut self, t: usize) -> Result<(), SynthError> {
        self.command(&json!({"op": "replay", "frame": t}))
    }

    /// One frame of the planned hands moving from `from` to `to`; a hand
    /// marked in `grasp` lets go and grips the vertices near `from` (the
    /// scripted hands let go at the first step).
    pub fn step(
        &mut self,
        from: &[[f64; 3]],
        to: &[[f64; 3]],
        grasp: &[bool],
    ) -> Result<(), SynthError> {
        if from.len() != self.hands || to.len() != self.hands || grasp.len() != self.hands {
            return Err(SynthError::InvalidOption {
                option: "hands".into(),
                problem: format!(
                    "the plant was started with {} hands, a step moves {}",
                    self.hands,
                    from.len()
                ),
            });
        }
        self.command(&json!({"op": "step", "from": from, "to": to, "grasp": grasp}))
    }

    /// One frame with the hands where they are.
    pub fn step_free(&mut self) -> Result<(), SynthError> {
        self.command(&json!({"op": "free"}))
    }

    /// Every grip let go.
    pub fn release(&mut self) -> Result<(), SynthError> {
        self.command(&json!({"op": "release"}))
    }

    pub fn state(&mut self) -> Result<PlantState, SynthError> {
        self.send(&json!({"op": "state"}))?;
        let answer = self.answer("state")?;
        if answer.particles != Some(self.particles) {
            self.broken = true;
            return Err(engine_error(format!(
                "the simulator sent {:?} particles, the scene has {}",
                answer.particles, self.particles
            )));
        }
        let mut bytes = vec![0u8; 2 * self.particles * 3 * 4];
        if let Err(e) = self.output.read_exact(&mut bytes) {
            self.broken = true;
            return Err(engine_error(format!("reading the state: {e}")));
        }
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        let points = |part: &[f32]| -> Vec<[f32; 3]> {
            part.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
        };
        let (x, v) = values.split_at(self.particles * 3);
        let state = PlantState {
            x: points(x),
            v: points(v),
        };
        if state.x.iter().flatten().any(|c| !c.is_finite()) {
            return Err(engine_error("the simulator sent non-finite positions"));
        }
        Ok(state)
    }

    fn command(&mut self, command: &serde_json::Value) -> Result<(), SynthError> {
        self.send(command)?;
        self.answer(command["op"].as_str().unwrap_or("command"))
            .map(|_| ())
    }

    fn send(&mut self, command: &serde_json::Value) -> Result<(), SynthError> {
        writeln!(self.input, "{command}")
            .and_then(|()| self.input.flush())
            .map_err(|e| engine_error(format!("sending `{}`: {e}", command["op"])))
    }

    fn answer(&mut self, what: &str) -> Result<Answer, SynthError> {
        let mut line = String::new();
        let read = self.output.read_line(&mut line).map_err(|e| {
            self.broken = true;
            engine_error(format!("reading the answer to `{what}`: {e}"))
        })?;
        if read == 0 {
            self.broken = true;
            let status = self.child.try_wait().ok().flatten();
            return Err(engine_error(format!(
                "the simulator stopped before answering `{what}` ({})",
                status.map_or("still running".to_string(), |s| s.to_string())
            )));
        }
        let answer: Answer = serde_json::from_str(&line).map_err(|e| {
            self.broken = true;
            engine_error(format!("the answer to `{what}` is not JSON ({e}): {line}"))
        })?;
        if !answer.ok {
            return Err(engine_error(format!(
                "`{what}`: {}",
                answer.error.unwrap_or_else(|| "failed".into())
            )));
        }
        Ok(answer)
    }
}

impl Drop for MujocoPlant {
    fn drop(&mut self) {
        // Ask it to stop (when it still follows the protocol); a child that
        // has not stopped then is killed.
        if !self.broken {
            let _ = writeln!(self.input, "{}", json!({"op": "quit"}));
            let _ = self.input.flush();
            let mut line = String::new();
            let _ = self.output.read_line(&mut line);
        }
        if !matches!(self.child.try_wait(), Ok(Some(_))) {
            let _ = self.child.kill();
        }
        let _ = self.child.wait();
    }
}

//! Distributed Compliant Actuators (method.md §4): particles near a hand
//! anchor are tied to it by spring-dampers with rest offsets captured at
//! grasp time, normalised by n_p^{-1/2} so several anchors do not stack.
//! The `Single` and `Rigid` modes are the paper's ablations.

use crate::neighbors::PointIndex;
use crate::real::{Real, Vec3, vec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ActuatorMode {
    /// Every anchor within the grasp radius (the method).
    Distributed,
    /// Only the nearest anchor per particle, no normalisation.
    Single,
    /// Hard Dirichlet constraint: coupled particles follow their anchors.
    Rigid,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActuatorConfig {
    pub mode: ActuatorMode,
    /// Spring gain, 1/s² (acceleration per metre of offset error).
    pub kp: f64,
    /// Damper gain, 1/s.
    pub kd: f64,
    /// Particles within this distance of an anchor at grasp time are tied.
    pub grasp_radius: f64,
}

impl Default for ActuatorConfig {
    fn default() -> Self {
        Self {
            mode: ActuatorMode::Distributed,
            kp: 3000.0,
            kd: 60.0,
            grasp_radius: 0.03,
        }
    }
}

/// One particle's tie to a hand anchor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Coupling {
    pub anchor: u32,
    /// Anchor minus particle at grasp time, metres.
    pub rest_offset: [f64; 3],
    /// Distance at grasp time, metres.
    pub capture_distance: f64,
}

/// The hands' hold on an object, carried from one world to another: each
/// particle's couplings in a caller's particle order, and which anchors
/// have grasped (they take hold of nothing more).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Grip {
    pub grasped: Vec<bool>,
    pub couplings: Vec<Vec<Coupling>>,
}

impl Grip {
    /// The grip of the particles `particles` of this one, in that order.
    pub fn subset(&self, particles: &[usize]) -> Grip {
        Grip {
            grasped: self.grasped.clone(),
            couplings: particles
                .iter()
                .map(|&i| self.couplings[i].clone())
                .collect(),
        }
    }
}

/// Couplings (particle slot, anchor, rest offset), grouped by particle.
#[derive(Clone, Debug)]
pub struct Actuators<T> {
    pub config: ActuatorConfig,
    pub(crate) grasped: Vec<bool>,
    /// `row_start[p]..row_start[p+1]` are particle p's couplings.
    pub(crate) row_start: Vec<u32>,
    pub(crate) anchor: Vec<u32>,
    pub(crate) rest_offset: Vec<Vec3<T>>,
    /// Distance at capture, used by `Single` to keep the nearest anchor.
    pub(crate) capture_distance: Vec<T>,
}

impl<T: Real> Actuators<T> {
    pub fn new(config: ActuatorConfig, particle_count: usize) -> Self {
        Self {
            config,
            grasped: Vec::new(),
            row_start: vec![0; particle_count + 1],
            anchor: Vec::new(),
            rest_offset: Vec::new(),
            capture_distance: Vec::new(),
        }
    }

    pub fn coupling_count(&self) -> usize {
        self.anchor.len()
    }

    /// How many anchors every later frame must provide: one past the highest
    /// anchor index any particle is tied to (0 when nothing is grasped).
    pub fn anchors_needed(&self) -> usize {
        self.anchor.iter().max().map_or(0, |&a| a as usize + 1)
    }

    /// Number of particles tied to at least one anchor.
    pub fn coupled_particle_count(&self) -> usize {
        self.row_start.windows(2).filter(|w| w[1] > w[0]).count()
    }

    /// The couplings as flat arrays: `row_start[p]..row_start[p + 1]`
    /// index particle p's anchors and rest offsets.
    pub fn coupling_arrays(&self) -> (&[u32], &[u32], &[Vec3<T>]) {
        (&self.row_start, &self.anchor, &self.rest_offset)
    }

    /// Whether an active anchor has not grasped yet (the next frame's
    /// grasp may then tie particles to it).
    pub fn grasp_pending(&self, active: &[bool]) -> bool {
        active
            .iter()
            .enumerate()
            .any(|(a, &on)| on && !self.grasped.get(a).copied().unwrap_or(false))
    }

    /// Anchors `a` of particle `p` with their rest offsets.
    pub fn couplings_of(&self, p: usize) -> impl Iterator<Item = (usize, Vec3<T>)> + '_ {
        let r = self.row_start[p] as usize..self.row_start[p + 1] as usize;
        self.anchor[r.clone()]
            .iter()
            .zip(&self.rest_offset[r])
            .map(|(&a, &o)| (a as usize, o))
    }

    /// Ties particles to every active anchor that has not grasped yet and
    /// now lies within the grasp radius of the object.
    pub fn grasp(&mut self, x: &[Vec3<T>], anchors: &[Vec3<T>], active: &[bool]) {
        if self.grasped.len() < anchors.len() {
            self.grasped.resize(anchors.len(), false);
        }
        let radius = self.config.grasp_radius;
        let candidates: Vec<usize> = (0..anchors.len())
            .filter(|&a| active.get(a).copied().unwrap_or(false) && !self.grasped[a])
            .collect();
        if candidates.is_empty() || x.is_empty() {
            return;
        }
        // Skip the k-d tree when no candidate is near the object's box.
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for p in x {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a].to_f64());
                hi[a] = hi[a].max(p[a].to_f64());
            }
        }
        let near_box = |q: &Vec3<T>| {
            (0..3).all(|a| q[a].to_f64() >= lo[a] - radius && q[a].to_f64() <= hi[a] + radius)
        };
        if !candidates.iter().any(|&a| near_box(&anchors[a])) {
            return;
        }
        let points: Vec<[f64; 3]> = x
            .iter()
            .map(|p| [p.x.to_f64(), p.y.to_f64(), p.z.to_f64()])
            .collect();
        let index = PointIndex::new(&points);
        let mut rows: Vec<Vec<(u32, Vec3<T>, T)>> = (0..x.len())
            .map(|p| {
                let r = self.row_start[p] as usize..self.row_start[p + 1] as usize;
                (r.clone())
                    .map(|i| {
                        (
                            self.anchor[i],
                            self.rest_offset[i],
                            self.capture_distance[i],
                        )
                    })
                    .collect()
            })
            .collect();
        for &a in &candidates {
            let q = &anchors[a];
            let found = index.within(&[q.x.to_f64(), q.y.to_f64(), q.z.to_f64()], radius);
            if found.is_empty() {
                continue;
            }
            self.grasped[a] = true;
            for (p, d) in found {
                let coupling = (a as u32, *q - x[p], T::lit(d));
                let row = &mut rows[p];
                if self.config.mode == ActuatorMode::Single {
                    if row.first().is_none_or(|old| coupling.2 < old.2) {
                        *row = vec![coupling];
                    }
                } else {
                    row.push(coupling);
                }
            }
        }
        self.row_start.clear();
        self.row_start.push(0);
        self.anchor.clear();
        self.rest_offset.clear();
        self.capture_distance.clear();
        for row in rows {
            for (a, o, d) in row {
                self.anchor.push(a);
                self.rest_offset.push(o);
                self.capture_distance.push(d);
            }
            self.row_start.push(self.anchor.len() as u32);
        }
    }

    /// Actuator acceleration of every particle (zero where uncoupled).
    pub fn accelerations(
        &self,
        x: &[Vec3<T>],
        v: &[Vec3<T>],
        anchor_x: &[Vec3<T>],
        anchor_v: &[Vec3<T>],
        out: &mut [Vec3<T>],
    ) {
        let kp = T::lit(self.config.kp);
        let kd = T::lit(self.config.kd);
        out.par_iter_mut().enumerate().for_each(|(p, a_out)| {
            let (s, e) = (self.row_start[p] as usize, self.row_start[p + 1] as usize);
            let mut a = Vec3::zeros();
            if e > s && self.config.mode != ActuatorMode::Rigid {
                for i in s..e {
                    let c = self.anchor[i] as usize;
                    a += ((anchor_x[c] - x[p]) - self.rest_offset[i]) * kp
                        + (anchor_v[c] - v[p]) * kd;
                }
                a /= T::lit(((e - s) as f64).sqrt());
            }
            *a_out = a;
        });
    }

    /// Rigid mode: coupled particles are placed where their anchors say.
    pub fn enforce_rigid(
        &self,
        x: &mut [Vec3<T>],
        v: &mut [Vec3<T>],
        anchor_x: &[Vec3<T>],
        anchor_v: &[Vec3<T>],
    ) {
        if self.config.mode != ActuatorMode::Rigid {
            return;
        }
        x.par_iter_mut()
            .zip(v.par_iter_mut())
            .enumerate()
            .for_each(|(p, (xp, vp))| {
                let (s, e) = (self.row_start[p] as usize, self.row_start[p + 1] as usize);
                if e == s {
                    return;
                }
                let n = T::lit((e - s) as f64);
                let mut target_x = Vec3::zeros();
                let mut target_v = Vec3::zeros();
                for i in s..e {
                    let c = self.anchor[i] as usize;
                    target_x += anchor_x[c] - self.rest_offset[i];
                    target_v += anchor_v[c];
                }
                *xp = target_x / n;
                *vp = target_v / n;
            });
    }

    /// The couplings of the particles in `slots`, in that order.
    pub(crate) fn grip_of(&self, slots: impl Iterator<Item = usize>) -> Grip {
        let couplings = slots
            .map(|p| {
                let r = self.row_start[p] as usize..self.row_start[p + 1] as usize;
                r.map(|i| Coupling {
                    anchor: self.anchor[i],
                    rest_offset: [0, 1, 2].map(|a| self.rest_offset[i][a].to_f64()),
                    capture_distance: self.capture_distance[i].to_f64(),
                })
                .collect()
            })
            .collect();
        Grip {
            grasped: self.grasped.clone(),
            couplings,
        }
    }

    /// Replaces the couplings by `grip`'s, whose particle `id_of_slot[s]`
    /// sits in slot `s`.
    pub(crate) fn set_grip(&mut self, grip: &Grip, id_of_slot: &[u32]) {
        self.grasped = grip.grasped.clone();
        self.row_start = vec![0];
        self.anchor.clear();
        self.rest_offset.clear();
        self.capture_distance.clear();
        for &id in id_of_slot {
            for c in &grip.couplings[id as usize] {
                self.anchor.push(c.anchor);
                self.rest_offset.push(vec3(c.rest_offset));
                self.capture_distance.push(T::lit(c.capture_distance));
            }
            self.row_start.push(self.anchor.len() as u32);
        }
    }

    /// Renumbers particle slots after the world reorders its particles.
    pub fn permute(&mut self, order: &[u32]) {
        let mut row_start = vec![0u32];
        let (mut anchor, mut offset, mut dist) = (Vec::new(), Vec::new(), Vec::new());
        for &old in order {
            let (s, e) = (
                self.row_start[old as usize] as usize,
                self.row_start[old as usize + 1] as usize,
            );
            anchor.extend_from_slice(&self.anchor[s..e]);
            offset.extend_from_slice(&self.rest_offset[s..e]);
            dist.extend_from_slice(&self.capture_distance[s..e]);
            row_start.push(anchor.len() as u32);
        }
        self.row_start = row_start;
        self.anchor = anchor;
        self.rest_offset = offset;
        self.capture_distance = dist;
    }
}

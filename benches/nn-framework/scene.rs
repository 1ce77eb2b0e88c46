// Shared synthetic scene of both programs (included with `include!`): a blob
// of particles on a 32³ grid, each with its 27 B-spline support nodes.
pub struct Scene {
    pub particles: usize,
    pub inputs: Vec<f32>,         // particles × 27
    pub node_index: Vec<u32>,     // particles × 27, compacted node ids
    pub node_weight: Vec<f32>,    // particles × 27
    pub node_encoding: Vec<f32>,  // nodes × 39
    pub nodes: usize,
}

pub fn scene(particles: usize) -> Scene {
    let mut state = 0x2545F4914F6CDD1Du64;
    let mut uniform = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f32 / (1u64 << 53) as f32
    };
    let dx = 1.0 / 32.0;
    let mut node_ids = std::collections::BTreeMap::new();
    let (mut node_index, mut node_weight, mut inputs) = (vec![], vec![], vec![]);
    for _ in 0..particles {
        let x = [0.3 + 0.4 * uniform(), 0.3 + 0.4 * uniform(), 0.4 + 0.2 * uniform()];
        for _ in 0..27 {
            inputs.push(uniform() - 0.5);
        }
        let base = x.map(|c| (c / dx - 0.5).floor() as i32);
        let fx = [0, 1, 2].map(|a| x[a] / dx - base[a] as f32);
        let w = fx.map(|f| [0.5 * (1.5 - f).powi(2), 0.75 - (f - 1.0).powi(2), 0.5 * (f - 0.5).powi(2)]);
        for i in 0..3 {
            for j in 0..3 {
                for k in 0..3 {
                    let key = (base[0] + i as i32, base[1] + j as i32, base[2] + k as i32);
                    let next = node_ids.len() as u32;
                    node_index.push(*node_ids.entry(key).or_insert(next));
                    node_weight.push(w[0][i] * w[1][j] * w[2][k]);
                }
            }
        }
    }
    let nodes = node_ids.len();
    let mut node_encoding = vec![0.0; nodes * 39];
    for (&(i, j, k), &id) in &node_ids {
        let x = [i, j, k].map(|c| c as f32 * dx - 0.5);
        let row = &mut node_encoding[id as usize * 39..][..39];
        row[..3].copy_from_slice(&x);
        for band in 0..6 {
            for a in 0..3 {
                let phase = (1 << band) as f32 * std::f32::consts::PI * x[a];
                row[3 + band * 6 + a] = phase.sin();
                row[3 + band * 6 + 3 + a] = phase.cos();
            }
        }
    }
    Scene { particles, inputs, node_index, node_weight, node_encoding, nodes }
}

pub fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2] * 1e3
}

//! Lucas–Kanade of one window under an affine warp with a gain and a bias:
//! the reference window T(u) (u an offset from its centre) is found in
//! the target image I where α I(c + A u) + β matches it best (Gauss–Newton
//! on the 8 parameters A, c, α, β). Translation-only windows stop matching
//! once a textured solid turns or tilts under other light; this fit
//! follows the window's shear, rotation and scale and its brightness.

/// A grey 8-bit image borrowed from a `Mat` (row-major, one byte a pixel).
#[derive(Clone, Copy, Debug)]
pub struct GreyView<'a> {
    pub pixels: &'a [u8],
    pub width: usize,
    pub height: usize,
}

impl GreyView<'_> {
    /// Bilinear value at (x, y) (pixel centres at integers); `None` outside.
    fn sample(&self, x: f32, y: f32) -> Option<f32> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        if x0 + 1 >= self.width || y0 + 1 >= self.height {
            return None;
        }
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let at = |xx: usize, yy: usize| f32::from(self.pixels[yy * self.width + xx]);
        let top = at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx;
        let bottom = at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx;
        Some(top * (1.0 - fy) + bottom * fy)
    }
}

/// Where a window was found: centre `c`, linear part `a` (row-major
/// 2×2), gain and bias.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowWarp {
    pub centre: [f32; 2],
    pub a: [f32; 4],
    pub gain: f32,
    pub bias: f32,
}

impl WindowWarp {
    /// A window at `centre` as in the reference.
    pub fn at(centre: [f32; 2]) -> Self {
        Self {
            centre,
            a: [1.0, 0.0, 0.0, 1.0],
            gain: 1.0,
            bias: 0.0,
        }
    }
}

impl WindowWarp {
    /// How far the warp is from a plain shift: the largest change of the
    /// linear part's entries or of the gain.
    pub fn departure(&self) -> f32 {
        let identity = [1.0, 0.0, 0.0, 1.0];
        self.a
            .iter()
            .zip(identity)
            .map(|(a, i)| (a - i).abs())
            .fold((self.gain - 1.0).abs(), f32::max)
    }
}

/// Settings of the window fit.
#[derive(Clone, Copy, Debug)]
pub struct AffineFit {
    /// Half the window's side, pixels.
    pub half: i32,
    pub iterations: usize,
    /// The residual's RMS over the reference window's contrast (its
    /// standard deviation) above which the fit is refused.
    pub max_relative_residual: f32,
}

/// Solves `n`×`n` `m x = b` by Gaussian elimination with partial pivoting.
fn solve<const N: usize>(mut m: [[f64; N]; N], mut b: [f64; N]) -> Option<[f64; N]> {
    for col in 0..N {
        let pivot = (col..N).max_by(|&i, &j| m[i][col].abs().total_cmp(&m[j][col].abs()))?;
        if m[pivot][col].abs() < 1e-12 {
            return None;
        }
        m.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..N {
            let f = m[row][col] / m[col][col];
            for k in col..N {
                m[row][k] -= f * m[col][k];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let s: f64 = (row + 1..N).map(|k| m[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / m[row][row];
    }
    Some(x)
}

/// Finds the window of `reference` centred at `origin` in `target`,
/// starting from `start`; `None` when it leaves the image, the system is
/// singular, the warp folds or stretches beyond 2×, or the match stays
/// poor.
pub fn fit_window(
    reference: &GreyView,
    origin: [f32; 2],
    target: &GreyView,
    start: WindowWarp,
    settings: &AffineFit,
) -> Option<WindowWarp> {
    let h = settings.half;
    let mut template = Vec::with_capacity(((2 * h + 1) * (2 * h + 1)) as usize);
    for j in -h..=h {
        for i in -h..=h {
            let (u, v) = (i as f32, j as f32);
            template.push(([u, v], reference.sample(origin[0] + u, origin[1] + v)?));
        }
    }
    let n = template.len() as f32;
    let mean = template.iter().map(|t| t.1).sum::<f32>() / n;
    let contrast = (template.iter().map(|t| (t.1 - mean).powi(2)).sum::<f32>() / n).sqrt();
    if contrast < 1.0 {
        return None;
    }
    // Parameters: a (4), c (2), gain, bias.
    let mut warp = start;
    let mut rms = f32::INFINITY;
    for _ in 0..settings.iterations {
        let mut normal = [[0.0f64; 8]; 8];
        let mut rhs = [0.0f64; 8];
        let mut sum_sq = 0.0f64;
        for &([u, v], t) in &template {
            let x = warp.centre[0] + warp.a[0] * u + warp.a[1] * v;
            let y = warp.centre[1] + warp.a[2] * u + warp.a[3] * v;
            let value = target.sample(x, y)?;
            let gx = 0.5 * (target.sample(x + 1.0, y)? - target.sample(x - 1.0, y)?);
            let gy = 0.5 * (target.sample(x, y + 1.0)? - target.sample(x, y - 1.0)?);
            let r = warp.gain * value + warp.bias - t;
            let (ggx, ggy) = (warp.gain * gx, warp.gain * gy);
            let jac = [
                f64::from(ggx * u),
                f64::from(ggx * v),
                f64::from(ggy * u),
                f64::from(ggy * v),
                f64::from(ggx),
                f64::from(ggy),
                f64::from(value),
                1.0,
            ];
            for p in 0..8 {
                rhs[p] -= jac[p] * f64::from(r);
                for q in p..8 {
                    normal[p][q] += jac[p] * jac[q];
                }
            }
            sum_sq += f64::from(r * r);
        }
        rms = (sum_sq as f32 / n).sqrt();
        for p in 0..8 {
            for q in 0..p {
                normal[p][q] = normal[q][p];
            }
            // A little damping keeps flat directions (a stripe's shear) still.
            normal[p][p] *= 1.0 + 1e-3;
        }
        let step = solve(normal, rhs)?;
        for k in 0..4 {
            warp.a[k] += step[k] as f32;
        }
        warp.centre[0] += step[4] as f32;
        warp.centre[1] += step[5] as f32;
        warp.gain += step[6] as f32;
        warp.bias += step[7] as f32;
        if step[4].abs() < 1e-3 && step[5].abs() < 1e-3 {
            break;
        }
    }
    let det = warp.a[0] * warp.a[3] - warp.a[1] * warp.a[2];
    let norm_sq = warp.a.iter().map(|a| a * a).sum::<f32>();
    let plausible = det > 0.25
        && det < 4.0
        && norm_sq < 8.0
        && warp.gain > 0.5
        && warp.gain < 2.0
        && warp.centre.iter().all(|c| c.is_finite());
    (plausible && rms <= settings.max_relative_residual * contrast).then_some(warp)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(x: f32, y: f32) -> f32 {
        110.0
            + 40.0 * (0.31 * x + 0.17 * y).sin()
            + 35.0 * (0.23 * x - 0.29 * y + 1.0).sin()
            + 30.0 * (0.41 * x + 0.05 * y + 2.0).cos()
    }

    fn image(width: usize, height: usize, value: impl Fn(f32, f32) -> f32) -> Vec<u8> {
        (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| value(x as f32, y as f32).round().clamp(0.0, 255.0) as u8)
            .collect()
    }

    /// A window turned by 20°, scaled by 1.1, shifted and dimmed to 80 %
    /// plus 15 grey levels is found within 0.1 px.
    #[test]
    fn a_turned_scaled_and_dimmed_window_is_found() {
        let (w, h) = (120, 100);
        let reference = image(w, h, texture);
        let (sin, cos) = 20f32.to_radians().sin_cos();
        let (s, centre0, centre1) = (1.1f32, [60.0f32, 50.0], [63.4f32, 47.9]);
        // target(centre1 + s R u) = 0.8 reference(centre0 + u) + 15
        let target = image(w, h, |x, y| {
            let (dx, dy) = ((x - centre1[0]) / s, (y - centre1[1]) / s);
            let (u, v) = (cos * dx + sin * dy, -sin * dx + cos * dy);
            0.8 * texture(centre0[0] + u, centre0[1] + v) + 15.0
        });
        fn view(pixels: &[u8], width: usize, height: usize) -> GreyView<'_> {
            GreyView {
                pixels,
                width,
                height,
            }
        }
        let settings = AffineFit {
            half: 7,
            iterations: 40,
            max_relative_residual: 0.2,
        };
        let found = fit_window(
            &view(&reference, w, h),
            centre0,
            &view(&target, w, h),
            WindowWarp::at([62.0, 49.0]),
            &settings,
        )
        .expect("found");
        let error = ((found.centre[0] - centre1[0]).powi(2)
            + (found.centre[1] - centre1[1]).powi(2))
        .sqrt();
        assert!(error < 0.1, "centre {:?}, error {error} px", found.centre);
        assert!((found.a[0] - s * cos).abs() < 0.03, "{:?}", found.a);
        // A window of another texture is refused.
        let other = image(w, h, |x, y| texture(y * 1.7 + 13.0, x * 0.6 - 5.0));
        assert!(
            fit_window(
                &view(&reference, w, h),
                centre0,
                &view(&other, w, h),
                WindowWarp::at([62.0, 49.0]),
                &settings
            )
            .is_none()
        );
    }
}

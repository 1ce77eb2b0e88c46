//! Shape loss: one-directional Chamfer distance from the visible observed
//! points to the predicted *surface* particles (method.md §7, §9: interior
//! particles are excluded, and the direction is observed → predicted).

use dm_mpm::neighbors::PointIndex;

use super::{LossError, LossValue, check_finite, check_len, norm2, sub};

/// Shared checks; returns the k-d tree over the surface particles, or
/// `None` when no point is visible (nothing to match).
fn surface_index(
    predicted: &[[f64; 3]],
    surface_count: usize,
    observed: &[[f64; 3]],
    visible: &[bool],
) -> Result<Option<PointIndex>, LossError> {
    check_len("visible", observed.len(), visible.len())?;
    if surface_count > predicted.len() {
        return Err(LossError::InvalidArgument {
            argument: "surface_count",
            reason: format!(
                "{surface_count} surface particles but only {} predicted particles",
                predicted.len()
            ),
        });
    }
    check_finite("observed", observed, |k| visible[k])?;
    let surface = &predicted[..surface_count];
    check_finite("predicted", surface, |_| true)?;
    if !visible.iter().any(|&v| v) {
        return Ok(None);
    }
    if surface.is_empty() {
        return Err(LossError::Empty {
            argument: "predicted surface (surface_count = 0)",
        });
    }
    // Rebuilt every call: the surface moves every frame.
    Ok(Some(PointIndex::new(surface)))
}

/// `L_shape = (1/V) Σ_{k visible} min_{s < surface_count} |x_s − o_k|²`,
/// the surface particles being the first `surface_count` of `predicted`.
///
/// The gradient goes to each observed point's nearest surface particle only:
/// `∂L/∂x_{s(k)} += (2/V)(x_{s(k)} − o_k)`. The `min` has a kink where two
/// particles are equally near; there the nearest-neighbour query breaks the
/// tie towards the lowest particle index, and the gradient of that active
/// branch is a valid subgradient. Interior particles (index ≥
/// `surface_count`) get zero gradient. The gradient has one entry per
/// predicted particle.
///
/// Squared distances for a smooth training loss; [`chamfer_error`] is the
/// plain-distance metric. No visible point → value 0, zero gradient.
pub fn shape_loss(
    predicted: &[[f64; 3]],
    surface_count: usize,
    observed: &[[f64; 3]],
    visible: &[bool],
) -> Result<LossValue, LossError> {
    let mut out = LossValue::zero(predicted.len());
    let Some(index) = surface_index(predicted, surface_count, observed, visible)? else {
        return Ok(out);
    };
    let count = visible.iter().filter(|&&v| v).count();
    let scale = 1.0 / count as f64;
    for (o, _) in observed.iter().zip(visible).filter(|&(_, &v)| v) {
        let Some(&(s, _)) = index.nearest(o, 1).first() else {
            return Err(LossError::Empty {
                argument: "predicted surface",
            });
        };
        let d = sub(&predicted[s], o);
        out.value += scale * norm2(&d);
        for a in 0..3 {
            out.grad[s][a] += 2.0 * scale * d[a];
        }
    }
    Ok(out)
}

/// The §9 Chamfer metric of one frame: mean over visible observed points of
/// the distance to the nearest predicted surface particle, metres; `None`
/// when no point is visible.
pub fn chamfer_error(
    predicted: &[[f64; 3]],
    surface_count: usize,
    observed: &[[f64; 3]],
    visible: &[bool],
) -> Result<Option<f64>, LossError> {
    let Some(index) = surface_index(predicted, surface_count, observed, visible)? else {
        return Ok(None);
    };
    let mut sum = 0.0;
    let mut count = 0usize;
    for (o, _) in observed.iter().zip(visible).filter(|&(_, &v)| v) {
        let Some(&(_, distance)) = index.nearest(o, 1).first() else {
            return Err(LossError::Empty {
                argument: "predicted surface",
            });
        };
        sum += distance;
        count += 1;
    }
    Ok(Some(sum / count as f64))
}

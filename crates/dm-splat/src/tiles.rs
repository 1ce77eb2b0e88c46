//! Binning of projected Gaussians into 16×16 pixel tiles, depth-sorted.
//!
//! A Gaussian is listed in every tile its square `[u − r, u + r] × [v − r,
//! v + r]` (r the 3σ radius) overlaps, with gsplat's rounding: tiles
//! `⌊(u − r)/16⌋ ..< ⌈(u + r)/16⌉`. Lists are built by a counting pass over
//! the Gaussians in index order (so each tile's list starts in index order),
//! then every tile's list is sorted by (depth, index) — a total order, so
//! the result is the same whatever the thread count.

use dm_mpm::real::Real;
use rayon::prelude::*;

use crate::project::Projected;

/// Tile edge in pixels.
pub const TILE_SIZE: u32 = 16;

/// Half-open range of tiles `[x0, x1) × [y0, y1)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TileRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl TileRect {
    pub const EMPTY: TileRect = TileRect {
        x0: 0,
        y0: 0,
        x1: 0,
        y1: 0,
    };

    /// Tiles overlapped by the square of half-width `radius` around `(u, v)`,
    /// clipped to the `tiles_x × tiles_y` grid.
    pub fn covering(u: f64, v: f64, radius: f64, tiles_x: u32, tiles_y: u32) -> TileRect {
        let tile = f64::from(TILE_SIZE);
        // Float → integer casts saturate, so huge or negative bounds clip.
        let clip = |value: f64, count: u32| value.clamp(0.0, f64::from(count)) as u32;
        let rect = TileRect {
            x0: clip(((u - radius) / tile).floor(), tiles_x),
            y0: clip(((v - radius) / tile).floor(), tiles_y),
            x1: clip(((u + radius) / tile).ceil(), tiles_x),
            y1: clip(((v + radius) / tile).ceil(), tiles_y),
        };
        if rect.x0 >= rect.x1 || rect.y0 >= rect.y1 {
            TileRect::EMPTY
        } else {
            rect
        }
    }

    pub fn is_empty(&self) -> bool {
        self.x0 >= self.x1 || self.y0 >= self.y1
    }

    pub fn area(&self) -> usize {
        if self.is_empty() {
            0
        } else {
            (self.x1 - self.x0) as usize * (self.y1 - self.y0) as usize
        }
    }
}

/// Per-tile lists of Gaussian indices, front to back.
#[derive(Debug, Clone)]
pub struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// Tile `t`'s list is `gaussian_ids[offsets[t]..offsets[t + 1]]`
    /// (tiles row-major).
    pub offsets: Vec<usize>,
    pub gaussian_ids: Vec<u32>,
}

impl TileBins {
    pub fn build<T: Real>(projected: &Projected<T>, tiles_x: u32, tiles_y: u32) -> TileBins {
        let tile_count = tiles_x as usize * tiles_y as usize;
        let mut counts = vec![0usize; tile_count + 1];
        for rect in &projected.tile_rect {
            for ty in rect.y0..rect.y1 {
                for tx in rect.x0..rect.x1 {
                    counts[(ty * tiles_x + tx) as usize + 1] += 1;
                }
            }
        }
        let mut offsets = counts;
        for t in 0..tile_count {
            offsets[t + 1] += offsets[t];
        }
        let mut cursor = offsets.clone();
        let mut gaussian_ids = vec![0u32; offsets[tile_count]];
        for (index, rect) in projected.tile_rect.iter().enumerate() {
            for ty in rect.y0..rect.y1 {
                for tx in rect.x0..rect.x1 {
                    let t = (ty * tiles_x + tx) as usize;
                    gaussian_ids[cursor[t]] = index as u32;
                    cursor[t] += 1;
                }
            }
        }
        // Sort each tile's segment by depth, ties by index: disjoint slices,
        // a total order, so any schedule gives the same lists.
        let depth = &projected.depth;
        let mut segments: Vec<&mut [u32]> = Vec::with_capacity(tile_count);
        let mut rest = gaussian_ids.as_mut_slice();
        for t in 0..tile_count {
            let (head, tail) = rest.split_at_mut(offsets[t + 1] - offsets[t]);
            segments.push(head);
            rest = tail;
        }
        segments.into_par_iter().for_each(|segment| {
            segment.sort_unstable_by(|&a, &b| {
                depth[a as usize]
                    .to_f64()
                    .total_cmp(&depth[b as usize].to_f64())
                    .then(a.cmp(&b))
            });
        });
        TileBins {
            tiles_x,
            tiles_y,
            offsets,
            gaussian_ids,
        }
    }

    pub fn tile_count(&self) -> usize {
        self.tiles_x as usize * self.tiles_y as usize
    }

    /// Total number of (tile, Gaussian) pairs.
    pub fn intersections(&self) -> usize {
        self.gaussian_ids.len()
    }

    pub fn tile_list(&self, tile: usize) -> &[u32] {
        &self.gaussian_ids[self.offsets[tile]..self.offsets[tile + 1]]
    }
}

//! Several particles' scalars side by side: the per-particle stress is
//! written once, generic over [`Lanes`], and runs on one particle (`f32`,
//! `f64`) or on a SIMD register of them (`f32x8`, `f64x4`). Every lane
//! does exactly the scalar's operations, so a particle's stress is
//! bitwise the same whichever lanes it shares a register with.
//!
//! The operations are associated functions with names of their own, so
//! they never shadow `RealField`'s methods on the scalar types.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// A scalar, or a register of scalars processed in lock step.
pub trait Lanes:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    type Scalar: Copy;
    /// Per-lane truth values of a comparison.
    type Mask: Copy;
    const WIDTH: usize;
    fn broadcast(x: Self::Scalar) -> Self;
    fn from_fn(f: impl FnMut(usize) -> Self::Scalar) -> Self;
    fn lane(x: Self, i: usize) -> Self::Scalar;
    fn square_root(x: Self) -> Self;
    fn absolute(x: Self) -> Self;
    /// Natural logarithm, lane by lane with the scalar's own function (so
    /// it matches the scalar path bitwise).
    fn natural_log(x: Self) -> Self;
    fn at_most(x: Self, bound: Self) -> Self::Mask;
    fn above(x: Self, bound: Self) -> Self::Mask;
    /// `mask ? yes : no`, lane by lane.
    fn choose(mask: Self::Mask, yes: Self, no: Self) -> Self;
    fn both(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    fn either(a: Self::Mask, b: Self::Mask) -> Self::Mask;
    fn none() -> Self::Mask;
    fn not(mask: Self::Mask) -> Self::Mask;
    fn all(mask: Self::Mask) -> bool;
    fn mask_lane(mask: Self::Mask, i: usize) -> bool;
}

macro_rules! impl_scalar_lanes {
    ($t:ty) => {
        impl Lanes for $t {
            type Scalar = $t;
            type Mask = bool;
            const WIDTH: usize = 1;
            #[inline(always)]
            fn broadcast(x: $t) -> Self {
                x
            }
            #[inline(always)]
            fn from_fn(mut f: impl FnMut(usize) -> $t) -> Self {
                f(0)
            }
            #[inline(always)]
            fn lane(x: Self, _: usize) -> $t {
                x
            }
            #[inline(always)]
            fn square_root(x: Self) -> Self {
                x.sqrt()
            }
            #[inline(always)]
            fn absolute(x: Self) -> Self {
                x.abs()
            }
            #[inline(always)]
            fn natural_log(x: Self) -> Self {
                x.ln()
            }
            #[inline(always)]
            fn at_most(x: Self, bound: Self) -> bool {
                x <= bound
            }
            #[inline(always)]
            fn above(x: Self, bound: Self) -> bool {
                x > bound
            }
            #[inline(always)]
            fn choose(mask: bool, yes: Self, no: Self) -> Self {
                if mask { yes } else { no }
            }
            #[inline(always)]
            fn both(a: bool, b: bool) -> bool {
                a && b
            }
            #[inline(always)]
            fn either(a: bool, b: bool) -> bool {
                a || b
            }
            #[inline(always)]
            fn none() -> bool {
                false
            }
            #[inline(always)]
            fn not(mask: bool) -> bool {
                !mask
            }
            #[inline(always)]
            fn all(mask: bool) -> bool {
                mask
            }
            #[inline(always)]
            fn mask_lane(mask: bool, _: usize) -> bool {
                mask
            }
        }
    };
}
impl_scalar_lanes!(f32);
impl_scalar_lanes!(f64);

macro_rules! impl_simd_lanes {
    ($simd:ty, $t:ty, $width:expr) => {
        impl Lanes for $simd {
            type Scalar = $t;
            type Mask = $simd;
            const WIDTH: usize = $width;
            #[inline(always)]
            fn broadcast(x: $t) -> Self {
                <$simd>::splat(x)
            }
            #[inline(always)]
            fn from_fn(f: impl FnMut(usize) -> $t) -> Self {
                <$simd>::new(std::array::from_fn(f))
            }
            #[inline(always)]
            fn lane(x: Self, i: usize) -> $t {
                x.to_array()[i]
            }
            #[inline(always)]
            fn square_root(x: Self) -> Self {
                x.sqrt()
            }
            #[inline(always)]
            fn absolute(x: Self) -> Self {
                x.abs()
            }
            #[inline(always)]
            fn natural_log(x: Self) -> Self {
                <$simd>::new(x.to_array().map(|v| v.ln()))
            }
            #[inline(always)]
            fn at_most(x: Self, bound: Self) -> Self {
                x.simd_le(bound)
            }
            #[inline(always)]
            fn above(x: Self, bound: Self) -> Self {
                x.simd_gt(bound)
            }
            #[inline(always)]
            fn choose(mask: Self, yes: Self, no: Self) -> Self {
                mask.bitselect(yes, no)
            }
            #[inline(always)]
            fn both(a: Self, b: Self) -> Self {
                a & b
            }
            #[inline(always)]
            fn either(a: Self, b: Self) -> Self {
                a | b
            }
            #[inline(always)]
            fn none() -> Self {
                <$simd>::splat(0.0)
            }
            #[inline(always)]
            fn not(mask: Self) -> Self {
                !mask
            }
            #[inline(always)]
            fn all(mask: Self) -> bool {
                mask.all()
            }
            #[inline(always)]
            fn mask_lane(mask: Self, i: usize) -> bool {
                mask.to_bitmask() >> i & 1 == 1
            }
        }
    };
}
impl_simd_lanes!(wide::f32x8, f32, 8);
impl_simd_lanes!(wide::f64x4, f64, 4);

/// A 3×3 matrix of lanes, row-major: `m.0[row][col]`.
#[derive(Clone, Copy, Debug)]
pub struct M3<L>(pub [[L; 3]; 3]);

impl<L: Lanes> M3<L> {
    #[inline(always)]
    pub fn from_fn(mut f: impl FnMut(usize, usize) -> L) -> Self {
        Self(std::array::from_fn(|r| std::array::from_fn(|c| f(r, c))))
    }

    #[inline(always)]
    pub fn transpose(&self) -> Self {
        Self::from_fn(|r, c| self.0[c][r])
    }

    #[inline(always)]
    pub fn matmul(&self, b: &Self) -> Self {
        Self::from_fn(|r, c| {
            self.0[r][0] * b.0[0][c] + self.0[r][1] * b.0[1][c] + self.0[r][2] * b.0[2][c]
        })
    }

    #[inline(always)]
    pub fn add(&self, b: &Self) -> Self {
        Self::from_fn(|r, c| self.0[r][c] + b.0[r][c])
    }

    #[inline(always)]
    pub fn sub(&self, b: &Self) -> Self {
        Self::from_fn(|r, c| self.0[r][c] - b.0[r][c])
    }

    #[inline(always)]
    pub fn scale(&self, s: L) -> Self {
        Self::from_fn(|r, c| self.0[r][c] * s)
    }

    /// `self + s I`.
    #[inline(always)]
    pub fn add_diagonal(&self, s: L) -> Self {
        let mut m = *self;
        for i in 0..3 {
            m.0[i][i] = m.0[i][i] + s;
        }
        m
    }

    #[inline(always)]
    pub fn trace(&self) -> L {
        self.0[0][0] + self.0[1][1] + self.0[2][2]
    }

    #[inline(always)]
    pub fn norm_squared(&self) -> L {
        let m = &self.0;
        let row = |r: usize| m[r][0] * m[r][0] + m[r][1] * m[r][1] + m[r][2] * m[r][2];
        row(0) + row(1) + row(2)
    }

    /// The determinant by cofactor expansion along the first row.
    #[inline(always)]
    pub fn determinant(&self) -> L {
        let m = &self.0;
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    }

    /// The cofactor matrix, `det(F) F⁻ᵀ`.
    #[inline(always)]
    pub fn cofactor(&self) -> Self {
        let m = &self.0;
        Self([
            [
                m[1][1] * m[2][2] - m[1][2] * m[2][1],
                m[1][2] * m[2][0] - m[1][0] * m[2][2],
                m[1][0] * m[2][1] - m[1][1] * m[2][0],
            ],
            [
                m[0][2] * m[2][1] - m[0][1] * m[2][2],
                m[0][0] * m[2][2] - m[0][2] * m[2][0],
                m[0][1] * m[2][0] - m[0][0] * m[2][1],
            ],
            [
                m[0][1] * m[1][2] - m[0][2] * m[1][1],
                m[0][2] * m[1][0] - m[0][0] * m[1][2],
                m[0][0] * m[1][1] - m[0][1] * m[1][0],
            ],
        ])
    }

    /// Lane `i` of every entry.
    #[inline(always)]
    pub fn lane(&self, i: usize) -> [[L::Scalar; 3]; 3] {
        std::array::from_fn(|r| std::array::from_fn(|c| L::lane(self.0[r][c], i)))
    }

    /// Lane `i` of entry (r, c) is `entry(i, r, c)`.
    #[inline(always)]
    pub fn gather(entry: impl Fn(usize, usize, usize) -> L::Scalar) -> Self {
        Self::from_fn(|r, c| L::from_fn(|i| entry(i, r, c)))
    }

    /// `mask ? yes : no`, lane by lane.
    #[inline(always)]
    pub fn choose(mask: L::Mask, yes: &Self, no: &Self) -> Self {
        Self::from_fn(|r, c| L::choose(mask, yes.0[r][c], no.0[r][c]))
    }
}

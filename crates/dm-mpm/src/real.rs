//! The float type the kernels are generic over: f32 for speed, f64 for
//! finite-difference gradient checks and precision parity tests.

use crate::lanes::{Lanes, M3};
use nalgebra::{Matrix3, RealField, Vector3};
use std::ops::{Add, AddAssign, Mul, Sub};

/// Four lanes of `T` in one SIMD register: a grid node (momentum or
/// velocity xyz, mass) is one `Lane4`, so the stencil loops of P2G and
/// G2P do one fused multiply-add per node instead of four scalar ones.
pub trait Lane4<T>:
    Copy
    + Send
    + Sync
    + Default
    + std::fmt::Debug
    + PartialEq
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + AddAssign
{
    fn from_array(a: [T; 4]) -> Self;
    fn splat(x: T) -> Self;
    fn to_array(self) -> [T; 4];
    /// `self * m + a`.
    fn mul_add(self, m: Self, a: Self) -> Self;
}

macro_rules! impl_lane4 {
    ($t:ty, $simd:ty) => {
        impl Lane4<$t> for $simd {
            #[inline(always)]
            fn from_array(a: [$t; 4]) -> Self {
                <$simd>::new(a)
            }
            #[inline(always)]
            fn splat(x: $t) -> Self {
                <$simd>::splat(x)
            }
            #[inline(always)]
            fn to_array(self) -> [$t; 4] {
                <$simd>::to_array(self)
            }
            #[inline(always)]
            fn mul_add(self, m: Self, a: Self) -> Self {
                <$simd>::mul_add(self, m, a)
            }
        }
    };
}
impl_lane4!(f32, wide::f32x4);
impl_lane4!(f64, wide::f64x4);

/// A scalar the simulator runs on (`f32` or `f64`).
pub trait Real:
    RealField
    + Copy
    + Send
    + Sync
    + Default
    + std::fmt::Debug
    + Lanes<Scalar = Self, Mask = bool>
    + 'static
{
    /// Four lanes of this scalar (see [`Lane4`]).
    type Lane4: Lane4<Self>;
    /// As many particles of this scalar as one AVX register holds (the
    /// per-particle stress runs on these, see [`crate::lanes`]).
    type Wide: Lanes<Scalar = Self>;
    /// Converts an `f64` constant (exact for f64, rounded for f32).
    fn lit(x: f64) -> Self;
    /// Converts to `f64` for reporting.
    fn to_f64(self) -> f64;
    /// Whether the value is neither NaN nor infinite.
    fn finite(self) -> bool;
    /// Converts a small index.
    fn from_index(i: usize) -> Self;
}

impl Real for f32 {
    type Lane4 = wide::f32x4;
    type Wide = wide::f32x8;
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn finite(self) -> bool {
        self.is_finite()
    }
    #[inline(always)]
    fn from_index(i: usize) -> Self {
        i as f32
    }
}

impl Real for f64 {
    type Lane4 = wide::f64x4;
    type Wide = wide::f64x4;
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn finite(self) -> bool {
        self.is_finite()
    }
    #[inline(always)]
    fn from_index(i: usize) -> Self {
        i as f64
    }
}

pub type Vec3<T> = Vector3<T>;
pub type Mat3<T> = Matrix3<T>;

/// Converts an `[f64; 3]` to a vector of `T`.
#[inline]
pub fn vec3<T: Real>(v: [f64; 3]) -> Vec3<T> {
    Vec3::new(T::lit(v[0]), T::lit(v[1]), T::lit(v[2]))
}

/// Casts a vector between float types.
#[inline]
pub fn cast_vec<A: Real, B: Real>(v: &Vec3<A>) -> Vec3<B> {
    Vec3::new(
        B::lit(v.x.to_f64()),
        B::lit(v.y.to_f64()),
        B::lit(v.z.to_f64()),
    )
}

/// Casts a matrix between float types.
#[inline]
pub fn cast_mat<A: Real, B: Real>(m: &Mat3<A>) -> Mat3<B> {
    m.map(|x| B::lit(x.to_f64()))
}

/// A matrix as a one-lane [`M3`].
#[inline(always)]
pub fn to_lanes<T: Real>(m: &Mat3<T>) -> M3<T> {
    M3::from_fn(|r, c| m[(r, c)])
}

/// A one-lane [`M3`] as a matrix.
#[inline(always)]
pub fn from_lanes<T: Real>(m: &M3<T>) -> Mat3<T> {
    Mat3::from_fn(|r, c| m.0[r][c])
}

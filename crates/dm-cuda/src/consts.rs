//! The substep constants as the kernels read them (`struct Consts` in
//! kernels/common.cuh, field for field).

use dm_mpm::actuators::ActuatorMode;
use dm_mpm::state::Consts;
use dm_mpm::{ActuatorConfig, Real};

#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct KernelConsts<T> {
    dt: T,
    dx: T,
    inv_dx: T,
    origin: [T; 3],
    gravity: [T; 3],
    grid_damping: T,
    particle_damping_factor: T,
    clip_lo: [T; 3],
    clip_hi: [T; 3],
    svd_lo: T,
    svd_hi: T,
    plastic_lo: T,
    plastic_hi: T,
    floor_up: [T; 3],
    floor_limit: T,
    floor_friction: T,
    drag_linear: T,
    drag_quadratic: T,
    empty_node_mass: T,
    kp: T,
    kd: T,
    res: i32,
    wall_cells: i32,
    has_plastic: i32,
    has_floor: i32,
    pure_neo_hookean: i32,
    /// 0: no couplings; 1: spring-dampers; 2: rigid.
    actuator_mode: i32,
}

// SAFETY: `#[repr(C)]` plain data (the float type and i32) whose layout
// matches the kernels' struct.
unsafe impl<T: cudarc::driver::DeviceRepr> cudarc::driver::DeviceRepr for KernelConsts<T> {}

impl<T: Real> KernelConsts<T> {
    pub(crate) fn new(
        k: &Consts<T>,
        pure_neo_hookean: bool,
        actuators: &ActuatorConfig,
        coupled: bool,
    ) -> Self {
        let v = |a: &dm_mpm::real::Vec3<T>| [a.x, a.y, a.z];
        let (plastic_lo, plastic_hi) = k.plastic.unwrap_or((T::one(), T::one()));
        let floor = k.floor.as_ref();
        Self {
            dt: k.dt,
            dx: k.dx,
            inv_dx: k.inv_dx,
            origin: v(&k.origin),
            gravity: v(&k.gravity),
            grid_damping: k.grid_damping,
            particle_damping_factor: k.particle_damping_factor,
            clip_lo: v(&k.clip_lo),
            clip_hi: v(&k.clip_hi),
            svd_lo: k.svd_lo,
            svd_hi: k.svd_hi,
            plastic_lo,
            plastic_hi,
            floor_up: floor.map_or([T::zero(); 3], |f| v(&f.up)),
            floor_limit: floor.map_or(T::zero(), |f| f.limit),
            floor_friction: floor.map_or(T::zero(), |f| f.friction),
            drag_linear: k.drag_linear,
            drag_quadratic: k.drag_quadratic,
            empty_node_mass: k.empty_node_mass,
            kp: T::lit(actuators.kp),
            kd: T::lit(actuators.kd),
            res: k.res as i32,
            wall_cells: k.wall_cells as i32,
            has_plastic: k.plastic.is_some() as i32,
            has_floor: floor.is_some() as i32,
            pure_neo_hookean: pure_neo_hookean as i32,
            actuator_mode: match (coupled, actuators.mode) {
                (false, _) => 0,
                (true, ActuatorMode::Rigid) => 2,
                (true, _) => 1,
            },
        }
    }
}

impl<T: Real> KernelConsts<T> {
    /// Every field's bits (floats widened to f64 exactly), so that two
    /// sets of constants compare bit for bit: NaN equals itself and −0
    /// differs from +0, as in what a kernel computes from them.
    fn bits(&self) -> impl Iterator<Item = u64> {
        let floats = [
            self.dt,
            self.dx,
            self.inv_dx,
            self.grid_damping,
            self.particle_damping_factor,
            self.svd_lo,
            self.svd_hi,
            self.plastic_lo,
            self.plastic_hi,
            self.floor_limit,
            self.floor_friction,
            self.drag_linear,
            self.drag_quadratic,
            self.empty_node_mass,
            self.kp,
            self.kd,
        ]
        .into_iter()
        .chain(self.origin)
        .chain(self.gravity)
        .chain(self.clip_lo)
        .chain(self.clip_hi)
        .chain(self.floor_up);
        let integers = [
            self.res,
            self.wall_cells,
            self.has_plastic,
            self.has_floor,
            self.pure_neo_hookean,
            self.actuator_mode,
        ];
        floats
            .map(|x| x.to_f64().to_bits())
            .chain(integers.map(|i| i as u64))
    }

    /// Whether `other` holds the same bits in every field: a graph that
    /// baked these constants in computes the same with `other`.
    pub(crate) fn same_bits(&self, other: &Self) -> bool {
        self.bits().eq(other.bits())
    }
}

/// A translation unit that compiles only when the kernels' `struct
/// Consts` has the size of [`KernelConsts`] in `precision` (a check
/// that the two layouts still agree).
pub fn layout_check_source(precision: crate::Precision) -> String {
    let size = match precision {
        crate::Precision::F32 => std::mem::size_of::<KernelConsts<f32>>(),
        crate::Precision::F64 => std::mem::size_of::<KernelConsts<f64>>(),
    };
    format!(
        "{}\nstatic_assert(sizeof(Consts) == {size}, \"struct Consts differs from KernelConsts\");\n",
        crate::kernels::source(precision)
    )
}

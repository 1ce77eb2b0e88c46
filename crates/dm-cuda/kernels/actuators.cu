// Distributed Compliant Actuators (actuators.rs): each coupled particle's
// spring-damper acceleration towards its anchors, normalised by the
// square root of its coupling count; in rigid mode, coupled particles
// placed where their anchors say after G2P. `anchor_x` holds this
// substep's anchor positions, `anchor_end` those at its end.

extern "C" __global__ void actuator_accel(
    Consts k, int n,
    const real* __restrict__ xs, const real* __restrict__ vs,
    const unsigned int* __restrict__ row_start, const unsigned int* __restrict__ anchor,
    const real* __restrict__ rest_offset,
    const real* __restrict__ anchor_x, const real* __restrict__ anchor_v,
    real* __restrict__ accel)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    unsigned int s = row_start[p], e = row_start[p + 1];
    v3 a = v3_zero();
    if (e > s && k.actuator_mode == 1) {
        v3 x = v3_load(xs + 3 * p);
        v3 v = v3_load(vs + 3 * p);
        for (unsigned int i = s; i < e; ++i) {
            unsigned int c = anchor[i];
            v3 spring = v3_sub(v3_sub(v3_load(anchor_x + 3 * c), x), v3_load(rest_offset + 3 * i));
            v3 damper = v3_sub(v3_load(anchor_v + 3 * c), v);
            a = v3_add(a, v3_add(v3_scale(spring, k.kp), v3_scale(damper, k.kd)));
        }
        a = v3_div(a, sqrt((real)(e - s)));
    }
    v3_store(accel + 3 * p, a);
}

extern "C" __global__ void enforce_rigid(
    int n,
    const unsigned int* __restrict__ row_start, const unsigned int* __restrict__ anchor,
    const real* __restrict__ rest_offset,
    const real* __restrict__ anchor_end, const real* __restrict__ anchor_v,
    real* __restrict__ xs, real* __restrict__ vs)
{
    int p = blockIdx.x * blockDim.x + threadIdx.x;
    if (p >= n) return;
    unsigned int s = row_start[p], e = row_start[p + 1];
    if (e == s) return;
    v3 tx = v3_zero(), tv = v3_zero();
    for (unsigned int i = s; i < e; ++i) {
        unsigned int c = anchor[i];
        tx = v3_add(tx, v3_sub(v3_load(anchor_end + 3 * c), v3_load(rest_offset + 3 * i)));
        tv = v3_add(tv, v3_load(anchor_v + 3 * c));
    }
    real count = (real)(e - s);
    v3_store(xs + 3 * p, v3_div(tx, count));
    v3_store(vs + 3 * p, v3_div(tv, count));
}

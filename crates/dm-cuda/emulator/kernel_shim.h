// Lets CUDA C kernels compile as host C++ for the CUDA emulator
// (driver.cc): the built-in indices, shared memory, barriers, warp
// shuffles and atomics, with every thread of a block a fiber of one host
// thread. Included before each precision's kernels.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>

namespace dm_emu {

struct uint3 {
    unsigned x, y, z;
};

struct ThreadContext {
    uint3 thread, block, block_dim, grid_dim;
    unsigned lane, warp;
};

const ThreadContext& context();
void syncthreads();
// Every live lane of the calling warp writes `bits`, waits for the others,
// and gets the bits of lane `source` (its own where `source` is outside
// the warp or has exited).
uint64_t warp_exchange(uint64_t bits, int source);
// Every live lane's `flag`, one bit per lane.
unsigned warp_ballot(bool flag);

template <class T>
inline uint64_t to_bits(T v) {
    static_assert(sizeof(T) <= 8, "shuffled values fit 8 bytes");
    uint64_t bits = 0;
    std::memcpy(&bits, &v, sizeof(T));
    return bits;
}

template <class T>
inline T from_bits(uint64_t bits) {
    T v;
    std::memcpy(&v, &bits, sizeof(T));
    return v;
}

// A kernel's parameters arrive as the driver API passes them: an array of
// pointers to each argument's value.
template <typename... A, std::size_t... I>
inline void call_with(void (*kernel)(A...), void** params, std::index_sequence<I...>) {
    kernel(*static_cast<std::remove_cv_t<std::remove_reference_t<A>>*>(params[I])...);
}

template <auto Kernel>
struct Thunk;

template <typename... A, void (*Kernel)(A...)>
struct Thunk<Kernel> {
    static void run(void** params) { call_with(Kernel, params, std::index_sequence_for<A...>{}); }
    // The bytes of each parameter, so that a captured launch can keep
    // copies of its arguments as the driver does.
    static constexpr int param_count = sizeof...(A);
    static constexpr std::size_t param_sizes[sizeof...(A) > 0 ? sizeof...(A) : 1] = {
        sizeof(std::remove_cv_t<std::remove_reference_t<A>>)...};
};

}  // namespace dm_emu

extern "C" void dm_emu_register(const char* precision, const char* name, void (*run)(void**),
                                int param_count, const std::size_t* param_sizes);

#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
// One block runs at a time, so a block's shared memory can be static.
#define __shared__ static
#define threadIdx (dm_emu::context().thread)
#define blockIdx (dm_emu::context().block)
#define blockDim (dm_emu::context().block_dim)
#define gridDim (dm_emu::context().grid_dim)
#define __syncthreads() dm_emu::syncthreads()

// The kernels' built-in functions, for one precision's namespace.
#define DM_EMU_BUILTINS                                                                  \
    using std::sqrt;                                                                     \
    using std::floor;                                                                    \
    using std::fabs;                                                                     \
    using std::tanh;                                                                     \
    using std::sin;                                                                      \
    using std::cos;                                                                      \
    using std::log;                                                                      \
    using std::fmin;                                                                     \
    using std::fmax;                                                                     \
    using std::isfinite;                                                                 \
    template <class T>                                                                   \
    inline T min(T a, T b) { return b < a ? b : a; }                                     \
    template <class T>                                                                   \
    inline T max(T a, T b) { return a < b ? b : a; }                                     \
    /* One fiber runs at a time: a read-modify-write cannot be interrupted. */          \
    template <class T>                                                                   \
    inline T atomicAdd(T* a, T v) { T old = *a; *a = old + v; return old; }             \
    template <class T>                                                                   \
    inline T atomicMin(T* a, T v) { T old = *a; if (v < old) *a = v; return old; }      \
    template <class T>                                                                   \
    inline T atomicMax(T* a, T v) { T old = *a; if (old < v) *a = v; return old; }      \
    template <class T>                                                                   \
    inline T __shfl_down_sync(unsigned, T v, unsigned delta) {                           \
        return dm_emu::from_bits<T>(dm_emu::warp_exchange(                              \
            dm_emu::to_bits(v), (int)(dm_emu::context().lane + delta)));                 \
    }                                                                                    \
    template <class T>                                                                   \
    inline T __shfl_up_sync(unsigned, T v, unsigned delta) {                             \
        return dm_emu::from_bits<T>(dm_emu::warp_exchange(                              \
            dm_emu::to_bits(v), (int)dm_emu::context().lane - (int)delta));              \
    }                                                                                    \
    inline unsigned __ballot_sync(unsigned, int flag) { return dm_emu::warp_ballot(flag != 0); } \
    inline int __ffs(unsigned x) { return x ? __builtin_ctz(x) + 1 : 0; }

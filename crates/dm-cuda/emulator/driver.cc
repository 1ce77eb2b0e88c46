// A CPU emulation of the part of the CUDA driver API the DeformMaster
// kernels are launched through (cudarc), for tests on machines without a
// GPU: device memory is host memory, every stream runs its work at once
// in call order, and a launch runs the kernel's blocks one after another,
// each block's threads as fibers of one host thread that switch at
// barriers and warp shuffles (x86-64 Linux). It checks what the kernels compute (indices,
// arithmetic, the host code around them), not the GPU's concurrency:
// atomics cannot race here, and lanes do not run in lock-step between
// barriers.
//
// Built as a shared library named libcuda.so together with the kernels
// compiled as C++ (kernel_shim.h); `cuModuleLoadData` ignores the PTX but
// for its precision marker (the `dm_precision_float` / `_double` entry)
// and finds each kernel by name.
#include "kernel_shim.h"

#include <sys/mman.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <mutex>
#include <string>
#include <vector>

typedef int CUresult;
typedef int CUdevice;
typedef unsigned long long CUdeviceptr;
typedef void* CUcontext;
typedef void* CUstream;
typedef void* CUevent;
typedef void* CUmodule;
typedef void* CUfunction;
typedef void* CUmemoryPool;

namespace {

const CUresult SUCCESS = 0;
const CUresult INVALID_VALUE = 1;
const CUresult NOT_FOUND = 500;
const CUresult LAUNCH_FAILED = 719;

using Run = void (*)(void**);

struct Kernel {
    std::string precision, name;
    Run run;
    std::vector<size_t> param_sizes;
};

struct Module {
    std::string precision;
};

std::map<std::pair<std::string, std::string>, Kernel>& registry() {
    static std::map<std::pair<std::string, std::string>, Kernel> kernels;
    return kernels;
}

// Launches and copies from several host threads take turns.
std::recursive_mutex& device_lock() {
    static std::recursive_mutex lock;
    return lock;
}

// ---- counts --------------------------------------------------------------
//
// With DM_CUDA_EMULATOR_COUNTS=FILE the emulator writes to FILE at exit
// what the run asked of the device: launches (and blocks) per kernel, and
// calls with their bytes per kind (copies each way, allocations, memsets,
// waits, event calls; kernel launches from the host, and work captured
// into graphs and replayed by graph launches, apart). These do not
// depend on how slowly the emulator runs them, so they show where a GPU
// run's launch and transfer latency goes.

struct Counts {
    std::map<std::string, std::pair<uint64_t, uint64_t>> launches;  // name: launches, blocks
    std::map<std::string, std::pair<uint64_t, uint64_t>> calls;  // kind: calls, bytes
    bool enabled = std::getenv("DM_CUDA_EMULATOR_COUNTS") != nullptr;

    void call(const char* kind, size_t bytes) {
        if (!enabled) return;
        std::lock_guard<std::recursive_mutex> guard(device_lock());
        auto& entry = calls[kind];
        entry.first += 1;
        entry.second += bytes;
    }

    ~Counts() {
        const char* path = std::getenv("DM_CUDA_EMULATOR_COUNTS");
        if (!path) return;
        FILE* out = std::fopen(path, "w");
        if (!out) return;
        for (const auto& [name, entry] : launches)
            std::fprintf(out, "launch %s %llu %llu\n", name.c_str(),
                         (unsigned long long)entry.first, (unsigned long long)entry.second);
        for (const auto& [kind, entry] : calls)
            std::fprintf(out, "%s %llu %llu\n", kind.c_str(),
                         (unsigned long long)entry.first, (unsigned long long)entry.second);
        std::fclose(out);
    }
};

Counts& counts() {
    static Counts c;
    return c;
}

// ---- fibers --------------------------------------------------------------
//
// Each thread of a block runs as a fiber: on a stack of its own, with the
// callee-saved registers switched without a system call. A thread that
// waits at a barrier switches straight to the next thread that can run;
// a thread that ends hands its stack to the next one if that one has not
// started, so a kernel without barriers runs all its threads on one stack
// without a switch. A waiting thread keeps its stack until it ends; stacks
// come from a pool.

enum State { NOT_STARTED, READY, AT_BLOCK_BARRIER, AT_WARP_BARRIER, DONE };

const size_t STACK_BYTES = 256 * 1024;
const int MAX_THREADS = 1024;
const uint32_t NO_ROUND = UINT32_MAX;

struct Stack {
    void* saved_sp = nullptr;
    char* memory = nullptr;
};

struct Thread {
    State state = DONE;
    Stack* stack = nullptr;
    dm_emu::ThreadContext indices;
    // Warp exchanges this thread has taken part in.
    uint32_t rounds = 0;
};

struct Block {
    Thread threads[MAX_THREADS];
    std::vector<Stack*> free_stacks;
    void* scheduler_sp = nullptr;
    Thread* current = nullptr;
    int count = 0;  // threads of the running block
    bool out_of_stacks = false;
    const Kernel* kernel = nullptr;
    void** params = nullptr;
    // Each lane's published value for the warp exchanges of even and odd
    // rounds, and the round it was published for (NO_ROUND: none).
    uint64_t slots[2][MAX_THREADS];
    uint32_t stamps[2][MAX_THREADS];
};

Block& block() {
    static Block b;
    return b;
}

}  // namespace

// Saves the callee-saved registers on the current stack, stores the stack
// pointer in *from, and resumes the stack `to` where it was saved (System V
// x86-64). MXCSR and the x87 control word are callee-saved too but left
// out: neither the kernels nor the scheduler change them.
extern "C" void dm_emu_switch(void** from, void* to);
asm(R"(
.pushsection .text
.globl dm_emu_switch
.type dm_emu_switch,@function
dm_emu_switch:
    pushq %rbp
    pushq %rbx
    pushq %r12
    pushq %r13
    pushq %r14
    pushq %r15
    movq %rsp, (%rdi)
    movq %rsi, %rsp
    popq %r15
    popq %r14
    popq %r13
    popq %r12
    popq %rbx
    popq %rbp
    ret
.size dm_emu_switch, .-dm_emu_switch
.popsection
)");

namespace {

// A fresh stack whose first switch enters fiber_main with the alignment
// of a call (rsp ≡ 8 mod 16 at entry).
[[noreturn]] void fiber_main();
void start_stack(Stack& s) {
    uintptr_t top = ((uintptr_t)(s.memory + STACK_BYTES)) & ~(uintptr_t)15;
    void** sp = (void**)(top - 16);
    *sp = (void*)&fiber_main;
    for (int r = 0; r < 6; ++r) *--sp = nullptr;
    s.saved_sp = sp;
}

Stack* take_stack() {
    Block& b = block();
    if (!b.free_stacks.empty()) {
        Stack* s = b.free_stacks.back();
        b.free_stacks.pop_back();
        return s;
    }
    void* memory = mmap(nullptr, STACK_BYTES, PROT_READ | PROT_WRITE,
                        MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
    if (memory == MAP_FAILED) return nullptr;
    Stack* s = new Stack();
    s->memory = static_cast<char*>(memory);
    start_stack(*s);
    return s;
}

// The thread after `from` in the pass's order that can run, or -1.
int next_runnable(const Block& b, int from) {
    for (int i = from + 1; i < b.count; ++i)
        if (b.threads[i].state == NOT_STARTED || b.threads[i].state == READY) return i;
    return -1;
}

// Makes thread `i` current, giving it a stack if it has not started; false
// when no stack could be had.
bool enter(Block& b, int i) {
    Thread& t = b.threads[i];
    if (t.state == NOT_STARTED) {
        t.stack = take_stack();
        if (!t.stack) {
            b.out_of_stacks = true;
            return false;
        }
        t.state = READY;
    }
    b.current = &t;
    return true;
}

// Leaves the stack `mine` (its place saved) for the next thread of the
// pass, or for the scheduler at the pass's end: threads switch to each
// other directly, in the order a scheduler's pass would run them.
void switch_onward(Stack* mine, int from) {
    Block& b = block();
    const int next = next_runnable(b, from);
    if (next < 0 || !enter(b, next)) {
        dm_emu_switch(&mine->saved_sp, b.scheduler_sp);
        return;
    }
    dm_emu_switch(&mine->saved_sp, b.current->stack->saved_sp);
}

// Runs the current thread's kernel; once it ends, runs the next thread of
// the pass on the same stack if that one has not started, else gives the
// stack back and switches to it.
[[noreturn]] void fiber_main() {
    for (;;) {
        Block& b = block();
        Thread* me = b.current;
        b.kernel->run(b.params);
        me->state = DONE;
        Stack* mine = me->stack;
        me->stack = nullptr;
        const int from = (int)(me - b.threads);
        const int next = next_runnable(b, from);
        if (next >= 0 && b.threads[next].state == NOT_STARTED) {
            Thread& t = b.threads[next];
            t.stack = mine;
            t.state = READY;
            b.current = &t;
            continue;
        }
        b.free_stacks.push_back(mine);
        switch_onward(mine, from);
    }
}

void wait(State state) {
    Block& b = block();
    Thread* me = b.current;
    me->state = state;
    switch_onward(me->stack, (int)(me - b.threads));
}

// Starts every thread's stack afresh and gives it back (a block that cannot
// go on); the block's threads count as ended.
void abandon_block(Block& b) {
    for (int i = 0; i < b.count; ++i) {
        Thread& t = b.threads[i];
        if (t.stack) {
            start_stack(*t.stack);
            b.free_stacks.push_back(t.stack);
            t.stack = nullptr;
        }
        t.state = DONE;
    }
}

bool run_block(const Kernel& kernel, void** params, dm_emu::uint3 grid, dm_emu::uint3 threads,
               dm_emu::uint3 index) {
    Block& b = block();
    const int count = (int)(threads.x * threads.y * threads.z);
    if (count > MAX_THREADS) {
        std::fprintf(stderr, "cuda emulator: %s: %d threads in a block (at most %d)\n",
                     kernel.name.c_str(), count, MAX_THREADS);
        return false;
    }
    b.kernel = &kernel;
    b.params = params;
    b.count = count;
    b.out_of_stacks = false;
    for (int i = 0; i < count; ++i) {
        Thread& t = b.threads[i];
        t.indices.thread = {(unsigned)(i % threads.x), (unsigned)((i / threads.x) % threads.y),
                            (unsigned)(i / (threads.x * threads.y))};
        t.indices.block = index;
        t.indices.block_dim = threads;
        t.indices.grid_dim = grid;
        t.indices.lane = (unsigned)(i % 32);
        t.indices.warp = (unsigned)(i / 32);
        t.state = NOT_STARTED;
        t.stack = nullptr;
        t.rounds = 0;
        b.stamps[0][i] = b.stamps[1][i] = NO_ROUND;
    }
    // Each pass runs the threads that can, in order, each until it ends or
    // waits at a barrier; between passes, barriers every thread (or every
    // lane of a warp) has reached are released.
    for (;;) {
        const int first = next_runnable(b, -1);
        const bool progressed = first >= 0;
        if (progressed && enter(b, first))
            dm_emu_switch(&b.scheduler_sp, b.current->stack->saved_sp);
        if (b.out_of_stacks) {
            std::fprintf(stderr, "cuda emulator: %s: no memory for a thread's stack\n",
                         kernel.name.c_str());
            abandon_block(b);
            return false;
        }
        bool live = false, all_at_block_barrier = true;
        for (int i = 0; i < count; ++i) {
            if (b.threads[i].state == DONE) continue;
            live = true;
            if (b.threads[i].state != AT_BLOCK_BARRIER) all_at_block_barrier = false;
        }
        if (!live) return true;
        bool released = false;
        if (all_at_block_barrier) {
            for (int i = 0; i < count; ++i)
                if (b.threads[i].state == AT_BLOCK_BARRIER) b.threads[i].state = READY;
            released = true;
        }
        for (int w = 0; w * 32 < count; ++w) {
            bool waiting = false, all = true;
            for (int i = w * 32; i < std::min(count, (w + 1) * 32); ++i) {
                State s = b.threads[i].state;
                if (s == DONE) continue;
                if (s == AT_WARP_BARRIER) waiting = true;
                else all = false;
            }
            if (waiting && all) {
                for (int i = w * 32; i < std::min(count, (w + 1) * 32); ++i)
                    if (b.threads[i].state == AT_WARP_BARRIER) b.threads[i].state = READY;
                released = true;
            }
        }
        if (!progressed && !released) {
            std::fprintf(stderr,
                         "cuda emulator: %s block (%u, %u, %u): threads wait at barriers that "
                         "can never be passed\n",
                         kernel.name.c_str(), index.x, index.y, index.z);
            // The waiting threads' stacks stay suspended mid-kernel.
            abandon_block(b);
            return false;
        }
    }
}

}  // namespace

namespace dm_emu {

const ThreadContext& context() { return block().current->indices; }

void syncthreads() { wait(AT_BLOCK_BARRIER); }

// One round of a warp's exchange: the calling lane publishes `bits` for
// its round, every live lane of the warp arrives, and `read(slots, lane's
// stamps, first lane's index, round)` reads what the lanes published for
// this round. Rounds alternate between two sets of slots: a lane can
// publish into a set again only two rounds later, after every lane has
// passed the barrier of the round between, and so has read this one.
template <class Read>
static auto warp_round(uint64_t bits, Read read) {
    Block& b = block();
    Thread& t = *b.current;
    const int me = (int)(&t - b.threads);
    const int warp_first = me - (int)t.indices.lane;
    const uint32_t round = t.rounds++;
    const int set = (int)(round & 1);
    b.slots[set][me] = bits;
    b.stamps[set][me] = round;
    wait(AT_WARP_BARRIER);
    return read(b.slots[set], b.stamps[set], warp_first, round);
}

uint64_t warp_exchange(uint64_t bits, int source) {
    return warp_round(bits, [&](const uint64_t* slots, const uint32_t* stamps, int warp_first,
                                uint32_t round) {
        const int from = warp_first + source;
        return source >= 0 && source < 32 && from < block().count && stamps[from] == round
                   ? slots[from]
                   : bits;
    });
}

unsigned warp_ballot(bool flag) {
    return warp_round(flag, [](const uint64_t* slots, const uint32_t* stamps, int warp_first,
                               uint32_t round) {
        unsigned bits = 0;
        for (int lane = 0; lane < 32 && warp_first + lane < block().count; ++lane)
            if (stamps[warp_first + lane] == round && slots[warp_first + lane]) bits |= 1u << lane;
        return bits;
    });
}

}  // namespace dm_emu

extern "C" void dm_emu_register(const char* precision, const char* name, void (*run)(void**),
                                int param_count, const size_t* param_sizes) {
    registry()[{precision, name}] =
        Kernel{precision, name, run, std::vector<size_t>(param_sizes, param_sizes + param_count)};
}

// ---- stream capture and graphs ------------------------------------------
//
// A stream in capture mode records its launches, memsets and
// device-to-device copies (the arguments copied, as the driver does)
// instead of running them; a graph launch replays them in order. Other
// work on a capturing stream is refused and invalidates the capture (its
// end then fails), as copies from or to the host, allocations and waits
// would on a GPU; so is a context-wide wait while any stream captures.

namespace {

struct Operation {
    enum Kind { LAUNCH, MEMSET, COPY } kind;
    const Kernel* kernel = nullptr;
    dm_emu::uint3 grid{}, threads{};
    std::vector<std::vector<unsigned char>> arguments;
    CUdeviceptr to = 0, from = 0;
    unsigned char value = 0;
    size_t bytes = 0;
};

struct Graph {
    std::vector<Operation> operations;
};

struct Stream {
    Graph* capture = nullptr;
    bool invalidated = false;
};

Graph* capturing(CUstream stream) {
    return stream ? static_cast<Stream*>(stream)->capture : nullptr;
}

const CUresult CAPTURE_UNSUPPORTED = 900;  // CUDA_ERROR_STREAM_CAPTURE_UNSUPPORTED
const CUresult CAPTURE_INVALIDATED = 901;  // CUDA_ERROR_STREAM_CAPTURE_INVALIDATED
const CUresult ILLEGAL_STATE = 401;        // CUDA_ERROR_ILLEGAL_STATE

// Streams capturing now (a context-wide wait is refused meanwhile).
std::atomic<int>& captures_open() {
    static std::atomic<int> open{0};
    return open;
}

// With DM_CUDA_EMULATOR_REFUSE_CAPTURED_LAUNCHES set, launches on a
// capturing stream are refused as a driver may refuse a capture, so the
// tests can check the host code's way back to launches one by one.
bool refuse_captured_launches() {
    static const bool refuse = std::getenv("DM_CUDA_EMULATOR_REFUSE_CAPTURED_LAUNCHES") != nullptr;
    return refuse;
}

// Adds a memset or a copy of `bytes` to a capture.
CUresult record(Graph* graph, Operation op, CUdeviceptr to, CUdeviceptr from, size_t bytes,
                const char* kind) {
    op.to = to;
    op.from = from;
    op.bytes = bytes;
    graph->operations.push_back(std::move(op));
    counts().call(kind, bytes);
    return SUCCESS;
}

// Refuses work a capture cannot hold: the capture is invalidated.
CUresult refuse_in_capture(CUstream stream) {
    static_cast<Stream*>(stream)->invalidated = true;
    return CAPTURE_UNSUPPORTED;
}

CUresult launch_now(const Kernel& kernel, void** params, dm_emu::uint3 grid, dm_emu::uint3 threads);

}  // namespace

// ---- the driver API ------------------------------------------------------

#define EXPORT extern "C" __attribute__((visibility("default")))

EXPORT CUresult cuInit(unsigned) { return SUCCESS; }
EXPORT CUresult cuDriverGetVersion(int* version) { *version = 13000; return SUCCESS; }
EXPORT CUresult cuDeviceGetCount(int* count) { *count = 1; return SUCCESS; }
EXPORT CUresult cuDeviceGet(CUdevice* device, int ordinal) {
    if (ordinal != 0) return INVALID_VALUE;
    *device = 0;
    return SUCCESS;
}
EXPORT CUresult cuDeviceGetAttribute(int* value, int attribute, CUdevice) {
    switch (attribute) {
        case 75: *value = 9; break;   // compute capability major
        case 76: *value = 0; break;   // minor
        case 10: *value = 32; break;  // warp size
        case 1: *value = 1024; break; // threads per block
        case 16: *value = 1; break;   // multiprocessors
        case 115: *value = 1; break;  // memory pools: stream-ordered allocation, as on the GPUs targeted
        default: *value = 0;          // the rest: absent
    }
    return SUCCESS;
}
EXPORT CUresult cuDeviceGetName(char* name, int length, CUdevice) {
    std::snprintf(name, (size_t)length, "CUDA emulator (CPU)");
    return SUCCESS;
}
EXPORT CUresult cuDeviceTotalMem_v2(size_t* bytes, CUdevice) { *bytes = (size_t)8 << 30; return SUCCESS; }
EXPORT CUresult cuMemGetInfo_v2(size_t* free, size_t* total) {
    *free = *total = (size_t)8 << 30;
    return SUCCESS;
}
static int the_context;
EXPORT CUresult cuDevicePrimaryCtxRetain(CUcontext* context, CUdevice) { *context = &the_context; return SUCCESS; }
EXPORT CUresult cuDevicePrimaryCtxRelease_v2(CUdevice) { return SUCCESS; }
EXPORT CUresult cuCtxSetCurrent(CUcontext) { return SUCCESS; }
EXPORT CUresult cuCtxGetCurrent(CUcontext* context) { *context = &the_context; return SUCCESS; }
EXPORT CUresult cuCtxSynchronize() {
    if (captures_open() > 0) return CAPTURE_UNSUPPORTED;
    counts().call("wait", 0);
    return SUCCESS;
}
EXPORT CUresult cuCtxGetStreamPriorityRange(int* least, int* greatest) { *least = *greatest = 0; return SUCCESS; }

EXPORT CUresult cuStreamCreate(CUstream* stream, unsigned) { *stream = new Stream(); return SUCCESS; }
EXPORT CUresult cuStreamCreateWithPriority(CUstream* stream, unsigned, int) { *stream = new Stream(); return SUCCESS; }
EXPORT CUresult cuStreamDestroy_v2(CUstream stream) { delete static_cast<Stream*>(stream); return SUCCESS; }
EXPORT CUresult cuStreamSynchronize(CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    counts().call("wait", 0);
    return SUCCESS;
}
EXPORT CUresult cuStreamWaitEvent(CUstream stream, CUevent, unsigned) {
    if (capturing(stream)) return refuse_in_capture(stream);  // no events are captured here
    counts().call("stream_wait_event", 0);
    return SUCCESS;
}
EXPORT CUresult cuStreamQuery(CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    return SUCCESS;
}

EXPORT CUresult cuEventCreate(CUevent* event, unsigned) {
    counts().call("event_create", 0);
    *event = new int(0);
    return SUCCESS;
}
EXPORT CUresult cuEventDestroy_v2(CUevent event) { delete static_cast<int*>(event); return SUCCESS; }
EXPORT CUresult cuEventRecord(CUevent, CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    counts().call("event_record", 0);
    return SUCCESS;
}
EXPORT CUresult cuEventQuery(CUevent) { return SUCCESS; }
EXPORT CUresult cuEventSynchronize(CUevent) { counts().call("wait", 0); return SUCCESS; }
EXPORT CUresult cuEventElapsedTime(float* ms, CUevent, CUevent) { *ms = 0; return SUCCESS; }
EXPORT CUresult cuEventElapsedTime_v2(float* ms, CUevent, CUevent) { *ms = 0; return SUCCESS; }

static CUresult allocate(CUdeviceptr* pointer, size_t bytes) {
    // 256-byte aligned like the device's; a zero-byte allocation still
    // gets an address of its own. Fresh memory reads as NaN (all bits
    // set), so a kernel reading what nobody wrote shows in the results.
    const size_t rounded = ((bytes + 255) / 256) * 256;
    void* memory = std::aligned_alloc(256, rounded > 0 ? rounded : 256);
    if (!memory) return 2;  // CUDA_ERROR_OUT_OF_MEMORY
    counts().call("alloc", bytes);
    std::memset(memory, 0xFF, rounded);
    *pointer = (CUdeviceptr)memory;
    return SUCCESS;
}
EXPORT CUresult cuMemAlloc_v2(CUdeviceptr* pointer, size_t bytes) { return allocate(pointer, bytes); }
EXPORT CUresult cuMemAllocAsync(CUdeviceptr* pointer, size_t bytes, CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    return allocate(pointer, bytes);
}
// The pool's memory is plain host memory; its attributes are counted.
static int the_pool;
EXPORT CUresult cuDeviceGetDefaultMemPool(CUmemoryPool* pool, CUdevice) {
    *pool = (CUmemoryPool)&the_pool;
    return SUCCESS;
}
EXPORT CUresult cuMemPoolSetAttribute(CUmemoryPool, int, void*) {
    counts().call("pool_attribute", 0);
    return SUCCESS;
}
EXPORT CUresult cuMemFree_v2(CUdeviceptr pointer) { std::free((void*)pointer); return SUCCESS; }
EXPORT CUresult cuMemFreeAsync(CUdeviceptr pointer, CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    std::free((void*)pointer);
    return SUCCESS;
}
EXPORT CUresult cuMemsetD8_v2(CUdeviceptr to, unsigned char value, size_t n) {
    std::lock_guard<std::recursive_mutex> guard(device_lock());
    std::memset((void*)to, value, n);
    counts().call("memset", n);
    return SUCCESS;
}
EXPORT CUresult cuMemsetD8Async(CUdeviceptr to, unsigned char value, size_t n, CUstream stream) {
    if (Graph* graph = capturing(stream)) {
        Operation op{Operation::MEMSET};
        op.value = value;
        return record(graph, std::move(op), to, 0, n, "captured_memset");
    }
    return cuMemsetD8_v2(to, value, n);
}
EXPORT CUresult cuMemcpyHtoD_v2(CUdeviceptr to, const void* from, size_t n) {
    std::lock_guard<std::recursive_mutex> guard(device_lock());
    std::memcpy((void*)to, from, n);
    counts().call("htod", n);
    return SUCCESS;
}
EXPORT CUresult cuMemcpyHtoDAsync_v2(CUdeviceptr to, const void* from, size_t n, CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    return cuMemcpyHtoD_v2(to, from, n);
}
EXPORT CUresult cuMemcpyDtoH_v2(void* to, CUdeviceptr from, size_t n) {
    std::lock_guard<std::recursive_mutex> guard(device_lock());
    std::memcpy(to, (const void*)from, n);
    counts().call("dtoh", n);
    return SUCCESS;
}
EXPORT CUresult cuMemcpyDtoHAsync_v2(void* to, CUdeviceptr from, size_t n, CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    return cuMemcpyDtoH_v2(to, from, n);
}
EXPORT CUresult cuMemcpyDtoD_v2(CUdeviceptr to, CUdeviceptr from, size_t n) {
    std::lock_guard<std::recursive_mutex> guard(device_lock());
    std::memmove((void*)to, (const void*)from, n);
    counts().call("dtod", n);
    return SUCCESS;
}
EXPORT CUresult cuMemcpyDtoDAsync_v2(CUdeviceptr to, CUdeviceptr from, size_t n, CUstream stream) {
    if (Graph* graph = capturing(stream)) {
        return record(graph, Operation{Operation::COPY}, to, from, n, "captured_dtod");
    }
    return cuMemcpyDtoD_v2(to, from, n);
}

EXPORT CUresult cuModuleLoadData(CUmodule* module, const void* image) {
    const char* ptx = static_cast<const char*>(image);
    std::string precision;
    if (std::strstr(ptx, "dm_precision_float")) precision = "float";
    else if (std::strstr(ptx, "dm_precision_double")) precision = "double";
    else {
        std::fprintf(stderr, "cuda emulator: the module names no precision (dm_precision_*)\n");
        return INVALID_VALUE;
    }
    *module = new Module{precision};
    return SUCCESS;
}
EXPORT CUresult cuModuleUnload(CUmodule module) { delete static_cast<Module*>(module); return SUCCESS; }
EXPORT CUresult cuModuleGetFunction(CUfunction* function, CUmodule module, const char* name) {
    auto& kernels = registry();
    auto found = kernels.find({static_cast<Module*>(module)->precision, name});
    if (found == kernels.end()) {
        std::fprintf(stderr, "cuda emulator: no kernel `%s`\n", name);
        return NOT_FOUND;
    }
    *function = &found->second;
    return SUCCESS;
}
EXPORT CUresult cuFuncGetAttribute(int* value, int, CUfunction) { *value = 0; return SUCCESS; }
EXPORT CUresult cuFuncSetAttribute(CUfunction, int, int) { return SUCCESS; }
EXPORT CUresult cuFuncSetCacheConfig(CUfunction, int) { return SUCCESS; }

EXPORT CUresult cuLaunchKernel(CUfunction function, unsigned gx, unsigned gy, unsigned gz,
                               unsigned bx, unsigned by, unsigned bz, unsigned, CUstream stream,
                               void** params, void**) {
    const Kernel& kernel = *static_cast<const Kernel*>(function);
    // The limits of the GPUs the kernels are built for (compute 7.5+).
    if (gx == 0 || gy == 0 || gz == 0 || gx > 2147483647u || gy > 65535 || gz > 65535 ||
        bx == 0 || by == 0 || bz == 0 || bx > 1024 || by > 1024 || bz > 64 ||
        bx * by * bz > 1024) {
        std::fprintf(stderr, "cuda emulator: %s: launch shape (%u, %u, %u) x (%u, %u, %u) out of limits\n",
                     kernel.name.c_str(), gx, gy, gz, bx, by, bz);
        return INVALID_VALUE;
    }
    const dm_emu::uint3 grid{gx, gy, gz}, threads{bx, by, bz};
    if (Graph* graph = capturing(stream)) {
        if (refuse_captured_launches()) return refuse_in_capture(stream);
        Operation op{Operation::LAUNCH};
        op.kernel = &kernel;
        op.grid = grid;
        op.threads = threads;
        for (size_t i = 0; i < kernel.param_sizes.size(); ++i) {
            const auto* bytes = static_cast<const unsigned char*>(params[i]);
            op.arguments.emplace_back(bytes, bytes + kernel.param_sizes[i]);
        }
        graph->operations.push_back(std::move(op));
        counts().call("captured_launch", 0);
        return SUCCESS;
    }
    counts().call("host_launch", 0);
    return launch_now(kernel, params, grid, threads);
}

namespace {
CUresult launch_now(const Kernel& kernel, void** params, dm_emu::uint3 grid, dm_emu::uint3 threads) {
    std::lock_guard<std::recursive_mutex> guard(device_lock());
    if (counts().enabled) {
        auto& entry = counts().launches[kernel.name];
        entry.first += 1;
        entry.second += (uint64_t)grid.x * grid.y * grid.z;
    }
    for (unsigned z = 0; z < grid.z; ++z)
        for (unsigned y = 0; y < grid.y; ++y)
            for (unsigned x = 0; x < grid.x; ++x)
                if (!run_block(kernel, params, grid, threads, {x, y, z})) return LAUNCH_FAILED;
    return SUCCESS;
}
}  // namespace

EXPORT CUresult cuStreamBeginCapture_v2(CUstream stream, int) {
    if (!stream) return CAPTURE_UNSUPPORTED;  // the legacy stream cannot capture
    Stream& s = *static_cast<Stream*>(stream);
    if (s.capture) return ILLEGAL_STATE;
    s.capture = new Graph();
    s.invalidated = false;
    captures_open() += 1;
    return SUCCESS;
}
EXPORT CUresult cuStreamEndCapture(CUstream stream, void** graph) {
    if (!capturing(stream)) return ILLEGAL_STATE;
    Stream& s = *static_cast<Stream*>(stream);
    captures_open() -= 1;
    *graph = nullptr;
    if (s.invalidated) {
        delete s.capture;
        s.capture = nullptr;
        return CAPTURE_INVALIDATED;
    }
    *graph = s.capture;
    s.capture = nullptr;
    counts().call("graph_capture", 0);
    return SUCCESS;
}
EXPORT CUresult cuStreamIsCapturing(CUstream stream, int* status) {
    *status = capturing(stream) ? 1 : 0;  // CU_STREAM_CAPTURE_STATUS_ACTIVE : _NONE
    return SUCCESS;
}
EXPORT CUresult cuGraphInstantiateWithFlags(void** exec, void* graph, unsigned long long) {
    *exec = new Graph(*static_cast<Graph*>(graph));
    return SUCCESS;
}
EXPORT CUresult cuGraphUpload(void*, CUstream) { return SUCCESS; }
EXPORT CUresult cuGraphLaunch(void* exec, CUstream stream) {
    if (capturing(stream)) return refuse_in_capture(stream);
    counts().call("graph_launch", 0);
    for (const Operation& op : static_cast<Graph*>(exec)->operations) {
        CUresult result = SUCCESS;
        switch (op.kind) {
            case Operation::LAUNCH: {
                std::vector<void*> params;
                for (const auto& argument : op.arguments)
                    params.push_back(const_cast<unsigned char*>(argument.data()));
                counts().call("replayed_launch", 0);
                result = launch_now(*op.kernel, params.data(), op.grid, op.threads);
                break;
            }
            case Operation::MEMSET: {
                std::lock_guard<std::recursive_mutex> guard(device_lock());
                std::memset((void*)op.to, op.value, op.bytes);
                counts().call("replayed_memset", op.bytes);
                break;
            }
            case Operation::COPY: {
                std::lock_guard<std::recursive_mutex> guard(device_lock());
                std::memmove((void*)op.to, (const void*)op.from, op.bytes);
                counts().call("replayed_dtod", op.bytes);
                break;
            }
        }
        if (result != SUCCESS) return result;
    }
    return SUCCESS;
}
EXPORT CUresult cuGraphExecDestroy(void* exec) { delete static_cast<Graph*>(exec); return SUCCESS; }
EXPORT CUresult cuGraphDestroy(void* graph) { delete static_cast<Graph*>(graph); return SUCCESS; }

EXPORT CUresult cuGetErrorName(CUresult error, const char** name) {
    static thread_local char text[32];
    std::snprintf(text, sizeof text, "CUDA_ERROR_%d", error);
    *name = text;
    return SUCCESS;
}
EXPORT CUresult cuGetErrorString(CUresult error, const char** text) { return cuGetErrorName(error, text); }

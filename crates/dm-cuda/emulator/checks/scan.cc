// The cell sort's two-level scan (sort.cu: scan_chunks, then scan_sums)
// run through the emulated driver API on seeded counts, against a running
// sum on the host. Usage: scan N [N ...]; prints one line per N and exits
// non-zero on the first mismatch or failed call.
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <vector>

typedef int CUresult;
typedef unsigned long long CUdeviceptr;
typedef void* CUmodule;
typedef void* CUfunction;
typedef void* CUstream;
extern "C" {
CUresult cuModuleLoadData(CUmodule*, const void*);
CUresult cuModuleGetFunction(CUfunction*, CUmodule, const char*);
CUresult cuMemAlloc_v2(CUdeviceptr*, size_t);
CUresult cuMemFree_v2(CUdeviceptr);
CUresult cuMemcpyHtoD_v2(CUdeviceptr, const void*, size_t);
CUresult cuMemcpyDtoH_v2(void*, CUdeviceptr, size_t);
CUresult cuLaunchKernel(CUfunction, unsigned, unsigned, unsigned, unsigned, unsigned, unsigned,
                        unsigned, CUstream, void**, void**);
}

// sort.cu's SCAN_CHUNK and SCAN_THREADS.
const int CHUNK = 1024;
const unsigned THREADS = 256;

int main(int argc, char** argv) {
    CUmodule module;
    CUfunction chunks, sums;
    if (cuModuleLoadData(&module, "dm_precision_float") ||
        cuModuleGetFunction(&chunks, module, "scan_chunks") ||
        cuModuleGetFunction(&sums, module, "scan_sums")) {
        std::fprintf(stderr, "the scan kernels are missing\n");
        return 2;
    }
    for (int a = 1; a < argc; ++a) {
        int n = std::atoi(argv[a]);
        int m = (n + CHUNK - 1) / CHUNK;
        std::vector<unsigned> counts(n);
        uint64_t state = 0x9e3779b97f4a7c15ull + (uint64_t)n;
        for (unsigned& c : counts) {
            state = state * 6364136223846793005ull + 1442695040888963407ull;
            c = (unsigned)(state >> 61);  // 0..7, as cells hold a few particles
        }
        CUdeviceptr data, chunk_sums;
        if (cuMemAlloc_v2(&data, 4 * (size_t)n) || cuMemAlloc_v2(&chunk_sums, 4 * (size_t)m) ||
            cuMemcpyHtoD_v2(data, counts.data(), 4 * (size_t)n))
            return 2;
        void* chunk_params[] = {&data, &n, &chunk_sums};
        void* sum_params[] = {&chunk_sums, &m};
        if (cuLaunchKernel(chunks, (unsigned)m, 1, 1, THREADS, 1, 1, 0, nullptr, chunk_params, nullptr) ||
            cuLaunchKernel(sums, 1, 1, 1, THREADS, 1, 1, 0, nullptr, sum_params, nullptr)) {
            std::fprintf(stderr, "n %d: a launch failed\n", n);
            return 1;
        }
        std::vector<unsigned> scanned(n), offsets(m);
        cuMemcpyDtoH_v2(scanned.data(), data, 4 * (size_t)n);
        cuMemcpyDtoH_v2(offsets.data(), chunk_sums, 4 * (size_t)m);
        cuMemFree_v2(data);
        cuMemFree_v2(chunk_sums);
        unsigned before = 0;
        for (int i = 0; i < n; ++i) {
            unsigned got = scanned[i] + offsets[i / CHUNK];
            if (got != before) {
                std::printf("n %d: value %d starts at %u, not %u\n", n, i, got, before);
                return 1;
            }
            before += counts[i];
        }
        std::printf("n %d (%d chunks): exclusive scan matches\n", n, m);
    }
    return 0;
}

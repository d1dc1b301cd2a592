// What the Hopper kernels (fused_hopper.cu, fused_gauss.cu) share: the warpgroup MMA on 128-byte-swizzled
// shared memory (m64n128k32, s32 += s8 x s8), its descriptors, and the mbarriers and bulk copies that feed it.

// shared-memory matrix descriptor: start >> 4 (bits 0-13), leading (K) byte offset >> 4 (16-29),
// stride (M/N) byte offset >> 4 (32-45), 128-byte swizzle (bits 62-63 = 1)
__device__ __forceinline__ unsigned long long mdesc(unsigned addr, unsigned lbo, unsigned sbo) {
    return (unsigned long long)((addr & 0x3FFFF) >> 4) | ((unsigned long long)(lbo >> 4) << 16)
         | ((unsigned long long)(sbo >> 4) << 32) | (1ull << 62);
}
// byte offset of 16-byte chunk j (of 8) of row r in the 128-byte-swizzled layout: 8-row x 128-byte
// atoms (1 KB), chunk j of row r stored at j ^ (r % 8) -- what the descriptor's swizzle mode reads
__device__ __forceinline__ int soff(int r, int j) { return (r >> 3) * 1024 + (r & 7) * 128 + ((j ^ (r & 7)) << 4); }
__device__ __forceinline__ void wg_mma(int* d, unsigned long long da, unsigned long long db, int scale) {
    asm volatile("{\n.reg .pred p;\nsetp.ne.b32 p, %66, 0;\n"
                 "wgmma.mma_async.sync.aligned.m64n128k32.s32.s8.s8 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, %32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, %48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}, %64, %65, p;\n}\n"
                 : "+r"(d[0]), "+r"(d[1]), "+r"(d[2]), "+r"(d[3]), "+r"(d[4]), "+r"(d[5]), "+r"(d[6]), "+r"(d[7]), "+r"(d[8]), "+r"(d[9]), "+r"(d[10]), "+r"(d[11]), "+r"(d[12]), "+r"(d[13]), "+r"(d[14]), "+r"(d[15]), "+r"(d[16]), "+r"(d[17]), "+r"(d[18]), "+r"(d[19]), "+r"(d[20]), "+r"(d[21]), "+r"(d[22]), "+r"(d[23]), "+r"(d[24]), "+r"(d[25]), "+r"(d[26]), "+r"(d[27]), "+r"(d[28]), "+r"(d[29]), "+r"(d[30]), "+r"(d[31]), "+r"(d[32]), "+r"(d[33]), "+r"(d[34]), "+r"(d[35]), "+r"(d[36]), "+r"(d[37]), "+r"(d[38]), "+r"(d[39]), "+r"(d[40]), "+r"(d[41]), "+r"(d[42]), "+r"(d[43]), "+r"(d[44]), "+r"(d[45]), "+r"(d[46]), "+r"(d[47]), "+r"(d[48]), "+r"(d[49]), "+r"(d[50]), "+r"(d[51]), "+r"(d[52]), "+r"(d[53]), "+r"(d[54]), "+r"(d[55]), "+r"(d[56]), "+r"(d[57]), "+r"(d[58]), "+r"(d[59]), "+r"(d[60]), "+r"(d[61]), "+r"(d[62]), "+r"(d[63])
                 : "l"(da), "l"(db), "r"(scale));
}


// the same MMA into d with d's old values ignored (D = A B): d written only, so the compiler need not keep
// what d held alive up to it
__device__ __forceinline__ void wg_mma_first(int* d, unsigned long long da, unsigned long long db) {
    asm volatile("wgmma.mma_async.sync.aligned.m64n128k32.s32.s8.s8 {%0, %1, %2, %3, %4, %5, %6, %7, %8, %9, %10, %11, %12, %13, %14, %15, %16, %17, %18, %19, %20, %21, %22, %23, %24, %25, %26, %27, %28, %29, %30, %31, %32, %33, %34, %35, %36, %37, %38, %39, %40, %41, %42, %43, %44, %45, %46, %47, %48, %49, %50, %51, %52, %53, %54, %55, %56, %57, %58, %59, %60, %61, %62, %63}, %64, %65, 0;\n"
                 : "=r"(d[0]), "=r"(d[1]), "=r"(d[2]), "=r"(d[3]), "=r"(d[4]), "=r"(d[5]), "=r"(d[6]), "=r"(d[7]), "=r"(d[8]), "=r"(d[9]), "=r"(d[10]), "=r"(d[11]), "=r"(d[12]), "=r"(d[13]), "=r"(d[14]), "=r"(d[15]), "=r"(d[16]), "=r"(d[17]), "=r"(d[18]), "=r"(d[19]), "=r"(d[20]), "=r"(d[21]), "=r"(d[22]), "=r"(d[23]), "=r"(d[24]), "=r"(d[25]), "=r"(d[26]), "=r"(d[27]), "=r"(d[28]), "=r"(d[29]), "=r"(d[30]), "=r"(d[31]), "=r"(d[32]), "=r"(d[33]), "=r"(d[34]), "=r"(d[35]), "=r"(d[36]), "=r"(d[37]), "=r"(d[38]), "=r"(d[39]), "=r"(d[40]), "=r"(d[41]), "=r"(d[42]), "=r"(d[43]), "=r"(d[44]), "=r"(d[45]), "=r"(d[46]), "=r"(d[47]), "=r"(d[48]), "=r"(d[49]), "=r"(d[50]), "=r"(d[51]), "=r"(d[52]), "=r"(d[53]), "=r"(d[54]), "=r"(d[55]), "=r"(d[56]), "=r"(d[57]), "=r"(d[58]), "=r"(d[59]), "=r"(d[60]), "=r"(d[61]), "=r"(d[62]), "=r"(d[63])
                 : "l"(da), "l"(db));
}
__device__ __forceinline__ void mbar_init(unsigned a, unsigned n) {
    asm volatile("mbarrier.init.shared::cta.b64 [%0], %1;\n" :: "r"(a), "r"(n) : "memory");
}
__device__ __forceinline__ void mbar_wait(unsigned a, unsigned parity) {
    asm volatile("{\n.reg .pred P1;\nLAB_WAIT:\n"
                 "mbarrier.try_wait.parity.shared::cta.b64 P1, [%0], %1;\n"
                 "@P1 bra DONE;\nbra LAB_WAIT;\nDONE:\n}\n" :: "r"(a), "r"(parity) : "memory");
}
__device__ __forceinline__ void mbar_expect(unsigned a, unsigned bytes) {
    asm volatile("mbarrier.arrive.expect_tx.shared::cta.b64 _, [%0], %1;\n" :: "r"(a), "r"(bytes) : "memory");
}
__device__ __forceinline__ void bulk_load(unsigned dst, const void* src, unsigned bytes, unsigned bar) {
    asm volatile("cp.async.bulk.shared::cluster.global.mbarrier::complete_tx::bytes [%0], [%1], %2, [%3];\n"
                 :: "r"(dst), "l"(src), "r"(bytes), "r"(bar) : "memory");
}

// lane 0 of the warp arrives (a predicated instruction: no branch for the compiler's wgmma analysis)
__device__ __forceinline__ void mbar_arrive_lane0(unsigned a, int lane) {
    asm volatile("{\n.reg .pred q;\nsetp.eq.s32 q, %1, 0;\n@q mbarrier.arrive.shared::cta.b64 _, [%0];\n}\n"
                 :: "r"(a), "r"(lane) : "memory");
}

// The block's mbarriers (thread 0, then the whole block waits): full[ST] (one arrival, the producer's
// bulk copy with its bytes), empty[ST] (the 8 MMA warps' arrivals), and B's.
__device__ __forceinline__ void init_stage_barriers(unsigned fullb, unsigned emptyb, unsigned bbar, int tid) {
    if (tid == 0) {
        for (int s = 0; s < ST; s++) { mbar_init(fullb + 8 * s, 1); mbar_init(emptyb + 8 * s, 8); }
        mbar_init(bbar, 1);
        asm volatile("fence.mbarrier_init.release.cluster;\n" ::: "memory");
    }
    __syncthreads();
}

// The producer's one thread: the block's whole B (nbt stages of 16384 bytes from Bsrc into sB) first,
// then `total` stages of A from Asrc through sA's ST stages, each stage's next copy waiting for its last
// use to be freed; stages from `nall` on repeat the last one (a block past the last row tile).
__device__ __forceinline__ void produce(unsigned char* sA, unsigned char* sB, const signed char* Asrc,
                                       const signed char* Bsrc, int nbt, int total, int nall,
                                       unsigned fullb, unsigned emptyb, unsigned bbar) {
    constexpr int TB = 16384;                      // a stage: 128 rows x 128 bytes (the kernels' TILE)
    mbar_expect(bbar, nbt * TB);
    bulk_load(smem_u32(sB), Bsrc, nbt * TB, bbar);
    for (int g = 0; g < total; g++) {
        const int s = g % ST;
        if (g >= ST) mbar_wait(emptyb + 8 * s, ((g / ST) - 1) & 1);   // its last use is done
        mbar_expect(fullb + 8 * s, TB);
        bulk_load(smem_u32(sA + s * TB), Asrc + (long long)min(g, nall - 1) * TB, TB, fullb + 8 * s);
    }
}

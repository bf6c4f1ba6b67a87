/* Density mip pyramid: one 2x2x2 averaging step (seed III.B.1, "downsampled the density
 * field to produce 11 density fields ... 1^3").
 *
 * The pyramid is one float buffer holding every level [z][y][x] (x fastest), level l of
 * n_l = base >> l voxels per side starting at element offset off_l. Level l+1 voxel
 * (x, y, z) is the mean of level l voxels (2x+i, 2y+j, 2z+k), i, j, k in {0, 1}, so the
 * total mass sum(density) * voxel_volume is the same on every level.
 *
 * mip_reduce
 *   data     float*  [sum n_l^3]   the whole pyramid; reads level l, writes level l+1
 *   src_off  int     element offset of level l;   n_dst  int  n_{l+1} (>= 1)
 *   dst_off  int     element offset of level l+1
 *   One work-item per destination voxel (global size padded: guarded by n_dst^3).
 *   Offsets fit in int: a 1024^3 base (the largest allowed) has 1.2e9 elements < 2^31.
 *
 * Twin: reference/pyramid.py (mip_chain). Host wrapper: clvol/kernels/pyramid.py.
 */


__kernel void mip_reduce(__global float *data, const int src_off, const int dst_off,
                         const int n_dst) {
    const int i = get_global_id(0);
    const int count = n_dst * n_dst * n_dst;
    if (i >= count) return;
    /* no '%': LLVM turns a / and % pair into a 'freeze' that Oclgrind cannot simulate */
    const int zy = i / n_dst, z = zy / n_dst;
    const int x = i - zy * n_dst, y = zy - z * n_dst;
    const size_t ns = (size_t)(2 * n_dst);
    __global const float *s = data + src_off;
    const size_t r0 = ((size_t)(2 * z) * ns + (size_t)(2 * y)) * ns + (size_t)(2 * x);
    const size_t sy = ns, sz = ns * ns;
    /* Pairwise sums in a fixed order: the twin adds in the same order. */
    float a = (s[r0] + s[r0 + 1]) + (s[r0 + sy] + s[r0 + sy + 1]);
    float b = (s[r0 + sz] + s[r0 + sz + 1]) + (s[r0 + sz + sy] + s[r0 + sz + sy + 1]);
    data[dst_off + i] = (a + b) * 0.125f;
}

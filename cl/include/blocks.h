/* The kernels' 16-float argument blocks: the medium's optical properties (medium.h,
 * MediumBlock) and the light's (light.h, LightBlock), each packed by one host function
 * (clvol/kernels/blocks.py medium_block, light_block; the C host takes the bundle's blocks as
 * they are and writes only what it changes at run time), so a new property reaches the ray
 * marcher and the path tracer through no argument list. A property the scene model declares
 * for the kernels (clvol/scenemodel.py ``declared(..., kernel=True)``) sits in a block's free
 * slots; the host passes its slot as -D MEDIUM_SLOT_<NAME> or -D LIGHT_SLOT_<NAME>, read
 * with block_float (block_float3 for an RGB one).
 *
 * Four float4s, not a float16: Oclgrind 21.10 with --uninitialized crashes on any float8 or
 * float16 kernel argument (tests/test_oclgrind.py runs every kernel there), and a struct of
 * float4s has the float16's layout and alignment on every device. Vectors are read whole or
 * component by component for the same reason: a .yzw shuffle crashed it in cl/raymarch.cl. */
#ifndef CLVOL_BLOCKS_H
#define CLVOL_BLOCKS_H

typedef struct {
    float4 q0, q1, q2, q3;      /* floats 0-3, 4-7, 8-11, 12-15 */
} Block16;

/* Float ``slot`` of a block. The slot is a build-time constant, so the selects fold to one
 * component. */
inline float block_float(const Block16 b, const int slot) {
    const float4 q = slot < 4 ? b.q0 : slot < 8 ? b.q1 : slot < 12 ? b.q2 : b.q3;
    const int c = slot & 3;
    return c == 0 ? q.x : c == 1 ? q.y : c == 2 ? q.z : q.w;
}

/* An RGB property from ``slot``: (r, g, b, 0). */
inline float4 block_float3(const Block16 b, const int slot) {
    return (float4)(block_float(b, slot), block_float(b, slot + 1), block_float(b, slot + 2),
                    0.0f);
}

#endif

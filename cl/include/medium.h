/* The medium block: the scene's optical properties, packed by one host function
 * (clvol/kernels/medium.py medium_block; the C host takes the bundle's block as it is and
 * writes only what it changes at run time) and passed as one 64-byte argument to the ray
 * marcher and the path tracer, so a new property reaches both kernels through no argument
 * list. Where each one sits: MEDIUM_* of constants.h (float index into the block), then the
 * declared properties at the slots the host passes (medium_float below).
 *
 *   density scale  sigma_t = density * density scale (1 / length)
 *   albedo         RGB single-scattering albedo
 *   lobe_g, lobe_w the phase lobes (phase.h): g and weight per lobe, unused lobes zero
 *
 * Four float4s, not a float16: Oclgrind 21.10 with --uninitialized crashes on any float8 or
 * float16 kernel argument (tests/test_oclgrind.py runs every kernel there), and a struct of
 * float4s has the float16's layout and alignment on every device. The albedo is built
 * component by component for the same reason: the .yzw shuffle crashed it in cl/raymarch.cl. */
#ifndef CLVOL_MEDIUM_H
#define CLVOL_MEDIUM_H

#include "constants.h"

typedef struct {
    float4 q0, q1, q2, q3;      /* floats 0-3, 4-7, 8-11, 12-15 */
} MediumBlock;

/* The accessors below are the slots of constants.h; a moved slot must move them too. */
#if MEDIUM_FLOATS != 16 || MEDIUM_DENSITY_SCALE != 0 || MEDIUM_ALBEDO != 1 || \
    MEDIUM_LOBE_G != 4 || MEDIUM_LOBE_W != 8
#error "medium.h: the accessors do not match the slots of constants.h"
#endif

#define MEDIUM_DENSITY_SCALE_OF(m) ((m).q0.x)
#define MEDIUM_ALBEDO_OF(m) ((float4)((m).q0.y, (m).q0.z, (m).q0.w, 0.0f))   /* RGB, w = 0 */
#define MEDIUM_LOBE_G_OF(m) ((m).q1)
#define MEDIUM_LOBE_W_OF(m) ((m).q2)

/* Float ``slot`` of the block: how a kernel reads a property the scene model declares
 * (clvol/scenemodel.py ``declared(..., kernel=True)``), by the slot the host passes as
 * -D MEDIUM_<NAME> (clvol/kernels/medium.py medium_defines): medium_float(m, MEDIUM_<NAME>).
 * The slot is a build-time constant, so the selects fold to one component. */
inline float medium_float(const MediumBlock m, const int slot) {
    const float4 q = slot < 4 ? m.q0 : slot < 8 ? m.q1 : slot < 12 ? m.q2 : m.q3;
    const int c = slot & 3;
    return c == 0 ? q.x : c == 1 ? q.y : c == 2 ? q.z : q.w;
}

#endif

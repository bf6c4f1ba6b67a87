/* The medium block (blocks.h): the scene's optical properties.
 *
 *   density scale  sigma_t = density * density scale (1 / length)
 *   albedo         RGB single-scattering albedo
 *   lobe_g, lobe_w the phase lobes (phase.h): g and weight per lobe, unused lobes zero
 *   then the medium's declared properties: medium_float(m, MEDIUM_SLOT_<NAME>), or
 *                  medium_float3 for an RGB one
 *
 * Where each one sits: MEDIUM_* of constants.h (float index into the block). */
#ifndef CLVOL_MEDIUM_H
#define CLVOL_MEDIUM_H

#include "blocks.h"
#include "constants.h"

typedef Block16 MediumBlock;

/* The accessors below are the slots of constants.h; a moved slot must move them too. */
#if MEDIUM_FLOATS != 16 || MEDIUM_DENSITY_SCALE != 0 || MEDIUM_ALBEDO != 1 || \
    MEDIUM_LOBE_G != 4 || MEDIUM_LOBE_W != 8
#error "medium.h: the accessors do not match the slots of constants.h"
#endif

#define MEDIUM_DENSITY_SCALE_OF(m) ((m).q0.x)
#define MEDIUM_ALBEDO_OF(m) ((float4)((m).q0.y, (m).q0.z, (m).q0.w, 0.0f))   /* RGB, w = 0 */
#define MEDIUM_LOBE_G_OF(m) ((m).q1)
#define MEDIUM_LOBE_W_OF(m) ((m).q2)
#define medium_float(m, slot) block_float(m, slot)
#define medium_float3(m, slot) block_float3(m, slot)

#endif

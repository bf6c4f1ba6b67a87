/* The light block (blocks.h): the scene's distant light.
 *
 *   direction   unit, toward the light (w = 0)
 *   irradiance  RGB (w = 0)
 *   then the light's declared properties: light_float(l, LIGHT_SLOT_<NAME>), or
 *               light_float3 for an RGB one
 *
 * Where each one sits: LIGHT_* of constants.h (float index into the block). */
#ifndef CLVOL_LIGHT_H
#define CLVOL_LIGHT_H

#include "blocks.h"
#include "constants.h"

typedef Block16 LightBlock;

#if LIGHT_FLOATS != 16 || LIGHT_DIRECTION != 0 || LIGHT_IRRADIANCE != 4
#error "light.h: the accessors do not match the slots of constants.h"
#endif

#define LIGHT_DIRECTION_OF(l) ((l).q0)
#define LIGHT_IRRADIANCE_OF(l) ((l).q1)
#define light_float(l, slot) block_float(l, slot)
#define light_float3(l, slot) block_float3(l, slot)

#endif

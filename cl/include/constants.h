/* Numbers that a kernel's code fixes and that the hosts need too (to size buffers, count
 * work-items or slice output rows). This file is the one place they are written:
 *   - the kernels that use one include this header;
 *   - the Python host reads this file (clvol/kernels/constants.py: kernel_constant), so it
 *     holds only include guards, comments and `#define NAME integer` lines;
 *   - the C host gets the ones it needs from the bundle's host.* keys, which clvol/bundle.py
 *     takes from the Python wrappers.
 * tests/test_constants.py checks that no Python module repeats one as a literal and that a
 * built program sees the values the Python host read.
 *
 * Numbers the host decides (the feature contract, the weight format, lane counts it measured
 * or chose for the device: LANES, cl/include/lanes.h)
 * go the other way: the host passes them as -D defines and the kernel stops with #error
 * without them (e.g. cl/include/mlp_core.h). */
#ifndef CLVOL_CONSTANTS_H
#define CLVOL_CONSTANTS_H

/* cl/raymarch.cl: pixels per row of the tile one work-item marches, one pixel per vector lane
 * (a tile is TILE x LANES / TILE pixels; the kernel's lane pattern is written for 4). */
#define TILE 4

/* cl/raymarch.cl: the most Wrenninge octaves (MS_OCTAVES) it evaluates. */
#define MS_MAX_OCTAVES 8

/* cl/transmittance.cl: padding of the sweep layout (lateral reach of a block of sweep steps,
 * explained there), and sweep steps per launch. */
#define SWEEP_PAD 17
#define SWEEP_BLOCK 16

/* cl/gather.cl bake_rows: voxels of a row per work-item (at most; n when the level is
 * narrower), in LANES-wide chunks. */
#define BAKE_SPAN 64

/* cl/pathtrace.cl: floats per path in the output row: background, order 1, orders >= 2
 * (RGB each), vertices, tracking steps, truncated; with -D PT_EMISSION then emission seen
 * unscattered and scattered >= 1 time (RGB each). */
#define PT_OUT_NO_EMISSION 12
#define PT_OUT_EMISSION 18

/* cl/pathtrace.cl -D PT_ORDER_BINS: exponents e < PT_ORDER_EXACT (a power of two,
 * 2^PT_ORDER_EXACT_LOG2) have a bin each, then every octave up to 2^PT_ORDER_END_LOG2 - 1
 * (> the kernel's PT_MAX_VERTICES) is split into PT_ORDER_SUB bins. */
#define PT_ORDER_EXACT 32
#define PT_ORDER_EXACT_LOG2 5
#define PT_ORDER_SUB 8
#define PT_ORDER_END_LOG2 17

/* cl/viewdepth.cl: the most query depths per block (VIEW_K) and sample rays per block side
 * (VIEW_RAYS) it supports (private arrays). */
#define VIEW_MAX_K 16
#define VIEW_MAX_RAYS 4

/* cl/include/medium.h: the medium block, one 16-float kernel argument (MediumBlock) of cl/raymarch.cl and
 * cl/pathtrace.cl: where each optical property sits (its first float) and the block's size.
 * Slots 12..15 are zero (free for the medium's declared properties). */
#define MEDIUM_FLOATS 16
#define MEDIUM_DENSITY_SCALE 0
#define MEDIUM_ALBEDO 1
#define MEDIUM_LOBE_G 4
#define MEDIUM_LOBE_W 8

/* cl/include/light.h: the light block, one 16-float kernel argument (LightBlock) of
 * cl/raymarch.cl and cl/pathtrace.cl: the distant light's direction and irradiance (first
 * floats, w = 0). Slots 8..15 are zero (free for the light's declared properties). */
#define LIGHT_FLOATS 16
#define LIGHT_DIRECTION 0
#define LIGHT_IRRADIANCE 4

#endif

"""Tunables, in one place (docs/DESIGN.md: never as magic numbers in kernels).

Each value is a default; the public functions take keyword arguments that override
it for one call.
"""

from __future__ import annotations

# --- storage -----------------------------------------------------------------------
#: Rows (and columns) of one square tile of the block-CSR grid.
DEFAULT_TILE_SIZE = 8192
#: The same for a colour store (3 values per pixel): 4096 pixels, so whole default image
#: tiles (8x8) and a multiple of 3 (a pixel's 3x3 block never straddles two tiles).
DEFAULT_COLOUR_TILE_SIZE = 12288
#: Most elements in one zarr chunk of a store's arrays (512 MiB of float32): a tile
#: row's indptr, indices and data are each one chunk file up to this size, so a row is
#: a handful of files whatever its entries (docs/FORMAT.md, "Why one group per tile
#: row"); larger arrays are cut into chunks of this many.
CHUNK_ELEMENTS = 1 << 27
#: zstd level for the tile arrays: level 1 is close to the best ratio on index
#: arrays at several times the speed of the default level 3.
ZSTD_LEVEL = 1
#: ...and for the tiles' float values, which zstd barely shrinks (1.10x at level 1 on
#: an inverse's tiles) at a cost: level -1 stores them nearly raw, encodes 4.5x and
#: decodes 14x faster (measured on the dense 384x512 corner's X). The files are still
#: zstd frames any zarr reader decodes.
ZSTD_LEVEL_VALUES = -1
#: ``BlockCSR.to_scipy`` refuses beyond this many bytes of CSR arrays.
TO_SCIPY_MAX_BYTES = 4 << 30

# --- images ------------------------------------------------------------------------
#: Edge of one image tile (pixels) for the image-tile-major pixel order.
DEFAULT_IMAGE_TILE = (8, 8)

#: Values (pixels x channels) an image file's header may declare when no transport shape
#: bounds it (bigT.images.check_declared_size; with one, H x W x 4). An image becomes a
#: float64 array, so this is 1 GiB: above any projector (8K is 33 M pixels) and the
#: monochrome sensors of scientific cameras (up to ~100 M), and below Pillow's own
#: refusal (179 M pixels). A forged header above it is refused before decoding, instead
#: of costing its declared size in memory.
IMAGE_MAX_VALUES = 1 << 27

# --- inverse -----------------------------------------------------------------------
#: Absolute threshold below which entries of each series term are dropped.
DEFAULT_PRUNE = 1e-5
#: An error is invisible on an 8-bit projector when the image the projector receives,
#: X d, is within this many 8-bit levels (of 255) of the exact inverse's T^-1 d at every
#: pixel: after the projector's own rounding (itself up to half a level) it is then the
#: exact inverse's image, up to one level on the pixels that straddle a rounding step.
INVISIBLE_LEVELS = 0.5
#: ``bigT invert`` with no series option (no --terms, --prune, --tol, ...) runs
#: ``invert_to_target`` at this relative error of the compensated probe images. The
#: probes' error and the projector image's worst 8-bit error go together: on the dense
#: 384x512 corner, 4 terms (benchmarks/bench_defaults.py), a worst probe of 1.0e-4 to
#: 1.4e-3 came with 1000 to 1660 times as many levels (9.6e-5: 0.16 level; 3.3e-4:
#: 0.40; 1.2e-3: 1.26), so the run's stop at SAFETY (0.8) times this target, 2.4e-4,
#: keeps that image within 0.24-0.40 level, under INVISIBLE_LEVELS; at 5e-4 (before
#: issue #30's speed goal) a stop at 4e-4 could have reached 0.66. It also skips the
#: measurement of term 3 there (its truncation part, 9.3e-4, is over MEASURE_WITHIN
#: times the safe target), a measurement that 5e-4 made and could not stop at.
#: Measured by benchmarks/bench_defaults.py to keep the projector image within
#: INVISIBLE_LEVELS of the exact inverse's on the scenes of the benchmarks (worst
#: 8-bit error; issue #30's run): 96x128 corner sparse 0.18, dense 0.13, Cornell box
#: 0.31 (a restart, 7 terms), hemispheres 0.10, convex and flat 0 (F^-1 alone);
#: 192x256 corner sparse 0.19, dense 0.12, Cornell box 0.25 (a restart, 7 terms),
#: hemispheres 0.09 (a restart, 5 terms), convex and flat 0; dense 384x512 corner 0.11
#: (3e-6, 4.5e-5, 9e-6, 4 terms). There a whole ``bigT invert`` process with no option
#: took, run interleaved with the one before (5e-4, decade prunes, 30x and 10x) and with
#: ``--terms 4 --prune 1e-5`` on a shared 2-core machine (load 6-9), 31.9-32.8 s of
#: CPU against 39.6-48.9 and 82.6-86.6 (2.6x fewer than the latter); wall 35-57 s
#: against 47-97 and 122-132.
DEFAULT_TARGET_ERROR = 3e-4
#: ``invert_to_target``'s power form prunes P_k (the next product's factor) at this
#: multiple of its prune, and M in the products after the first term at this one.
#: Measured on the dense 384x512 corner (explicit 4-term runs, benchmarks/
#: bench_defaults.py's measure; prune, feed, operator: multiply-adds, the projector
#: image's worst error in 8-bit levels): prune 1e-5 alone 1.2e11, 0.62;
#: 3e-6, 1e-4, 1e-5 (the README's recommendation before issue #30) 1.1e10, 1.26: P_k
#: pruned at 1e-4 drops entries of one sign, which shifts smooth images (a cliff:
#: 1e-6, 1e-4, 1e-5 also 1.30); 1e-6, 3e-5, 1e-5 (30x and 10x of a decade prune,
#: the default before) 2.7e10, 0.13; 3e-6, 3e-5, 1e-5 the same multiply-adds, 0.16,
#: with a quarter fewer entries in X (3.3e7 against 4.5e7: cheaper merges, writes and
#: measurements); 3e-6, 5e-5, 1e-5 2.2e10, 0.13; 3e-6, 3e-5, 2e-5 2.2e10, 0.23;
#: 3e-6, 3e-5, 3e-5 1.9e10, 0.40; 1e-5, 3e-5, 1e-5 2.7e10, 0.38 (the prune's error
#: is not carried by a bounce). The feed and the operator thresholds set the error
#: of the terms after the first, the prune that of X itself. With the prune on
#: 1-3 steps (3e-6 there, target.PRUNE_GRID), 15x and 3x give 3e-6, 4.5e-5, 9e-6,
#: below the feed's cliff by 2x.
TARGET_FEED_RATIO = 15.0
TARGET_OPERATOR_RATIO = 3.0
#: Largest condition number of a pixel's 3x3 colour block of F (a colour transport's
#: first bounce) that the engine inverts; a pixel above it is refused, or left out
#: with first_bounce="diag-skip-ill". The block's inverse carries the relative error of
#: its entries times the condition number: float32 entries (2^-24 = 6e-8) then give
#: F^-1 to 6e-4, under an 8-bit level (1/255 = 4e-3); past it, the pixel's channels are
#: ones the camera cannot tell apart, and F^-1 is mostly noise.
COLOUR_BLOCK_MAX_CONDITION = 1e4
#: Random probes z used to estimate ||I - T X||_F by r = z - T (X z).
RESIDUAL_PROBES = 4
#: The spectral radius of M is computed before the first product (bigT.spectral):
#: densely up to this many unknowns (one block product of the identity)...
SPECTRAL_RADIUS_DENSE_MAX = 256
#: ...above, by ARPACK's Arnoldi: the Ritz values of largest modulus it converges (a
#: +-rho pair or a complex pair needs more than one), the Krylov basis size,
SPECTRAL_RADIUS_RITZ = 4
SPECTRAL_RADIUS_NCV = 20
#: its relative tolerance (the ground truth of scenes asks for SCENE_SPECTRAL_RTOL),
SPECTRAL_RADIUS_RTOL = 1e-4
#: and the operator products after which it gives up (an uncertain estimate).
SPECTRAL_RADIUS_MAX_PRODUCTS = 600
#: Where M = -|M| (a transport with no negative entry, F = diag T), the engine first
#: brackets rho with Collatz-Wielandt bounds (bigT.spectral): about this many passes
#: over M (block products: a power step's one vector, a lower bound's one per support;
#: one lower-bound pass may follow the last), stopping once the bracket's width is
#: this fraction of its top,
SPECTRAL_RADIUS_CW_MAX_PASSES = 24
#: (this many while the bracket's top is under SPECTRAL_RADIUS_CW_ACCEPT: ARPACK, its
#: alternative, takes ~50 products),
SPECTRAL_RADIUS_CW_MAX_PASSES_LOW = 36
SPECTRAL_RADIUS_CW_RTOL = 0.02
#: A bracket wider than that is still taken when its top is under this (the series
#: then at least halves its error per term: a few % on rho change nothing a user
#: plans); else ARPACK refines it.
SPECTRAL_RADIUS_CW_ACCEPT = 0.5
#: ...when it is at most this fraction of its top wide (the lower bound still lags).
SPECTRAL_RADIUS_CW_WIDE = 0.1
#: the lower bound taken on the pixels whose power-iteration vector is at least one of
#: these fractions of its largest entry, in (0, 1], the best of them (one block
#: product: 1 % was the best single cut on the corner scenes, 1e-9 on the open
#: Cornell box),
SPECTRAL_RADIUS_CW_SUPPORTS = (1e-2, 1e-9)
#: and the iteration shifted by this fraction of the upper bound (v <- |M| v + s v keeps
#: v > 0 and breaks the +-rho oscillation of two walls that only see each other).
SPECTRAL_RADIUS_CW_SHIFT = 0.1
#: Where M has entries of both signs (colour: F^-1's blocks have negative entries), the
#: bracket's top on rho(|M|) >= rho(M) is taken as rho's upper bound when under this:
#: the series then provably converges, its error falling at least 10 % per term; nearer
#: 1, where 1 - rho sets the terms needed (and the bound may hold 1 while rho does not),
#: ARPACK computes rho itself.
SPECTRAL_RADIUS_ABS_ACCEPT = 0.9
#: A term whose residual estimate grew from the previous term's and exceeds the smallest
#: one so far by this factor stops the run (the series diverges). Not any growth: a
#: convergent series with a non-normal M (rho < 1 <= ||M||) or at its pruning floor may
#: grow for a term or two, by 40 % measured; a diverging one grows without end.
RESIDUAL_GROWTH = 2.0

#: Global colour mixing (bigT.algorithms.mixing): T un-mixed by one 3x3 C and P is
#: taken as channel-diagonal when its cross-channel entries are below this fraction of
#: its in-channel ones (Frobenius). A float32 entry carries a relative rounding of
#: 6e-8, which un-mixing amplifies by at most cond(C) cond(P) (a truly global T
#: measures about 1e-7 with realistic cross-talk); 1e-5 leaves room for cond(C) cond(P)
#: up to ~100, is the size of the default prune (what dropping the residue changes in
#: T is below what the series drops), and a per-pixel variation of the mixing of 0.1 %
#: already measures ~1e-3. For float64 stores the same reasoning gives 1e-10.
GLOBAL_MIXING_RTOL = 1e-5
GLOBAL_MIXING_RTOL_FLOAT64 = 1e-10
#: A pixel's 3x3 block (or a given mixing) with a larger condition number is not used
#: to estimate (or accepted as) a mixing: its inverse would amplify rounding beyond
#: the tolerance above.
GLOBAL_MIXING_MAX_COND = 1e4
#: The estimate from T's diagonal blocks samples this many well-conditioned pixels and
#: makes this many tries (another reference block and random combination each).
GLOBAL_MIXING_CANDIDATES = 256
GLOBAL_MIXING_TRIES = 4
#: Entries of T un-mixed at once (the global path's split): ~25 bytes each in flight.
GLOBAL_MIXING_CHUNK_ENTRIES = 1 << 21

#: A pass has at least this many row blocks (tasks) per thread of the scheduler: the
#: term stores' tile size is T's, halved until it gives that many (a cluster's threads
#: all get work, and a slow block does not leave the others idle at the end)...
TASKS_PER_THREAD = 4
#: ...but a row block keeps at least this many rows: below it the per-task overhead
#: (opening stores, reading T's tiles, writing tile files) outweighs the product.
MIN_BLOCK_ROWS = 1024

#: Seconds to wait for a dask scheduler given by address before giving up.
SCHEDULER_CONNECT_SECONDS = 10

# --- compensation -------------------------------------------------------------------
#: Frames streamed against each row tile of X at once.
DEFAULT_BATCH = 64

# --- kernels -------------------------------------------------------------------------
#: Threads the kernel wrappers split row ranges over (None: one per CPU core). Pass
#: ``n_threads=1`` from code that already runs tiles in parallel (e.g. dask threads).
KERNEL_THREADS = None
#: Idle workspaces of the grouped product kernel kept for reuse (each ~100 bytes per
#: column of the product: one per kernel call in flight is what a run reuses).
KERNEL_WORKSPACES_KEPT = 4
#: Row ranges per thread, cut to equal work, so one slow range does not idle a core.
KERNEL_CHUNKS_PER_THREAD = 4
#: Kernel calls with at most this many multiply-adds (products) or entries (the rest)
#: run on numpy/scipy instead of numba (bigT.kernels._small): as fast at that size, and
#: a run that only has such calls never imports numba nor compiles a kernel.
KERNEL_NUMPY_MAX_WORK = 20_000
#: Products with fewer multiply-adds than this run on the calling thread only.
KERNEL_MIN_PARALLEL_WORK = 200_000
#: ...and products of a sparse matrix with dense columns (spmm_dense) with fewer
#: entries x columns than this: a multiply-add there costs a fifth of a sparse
#: product's, so handing half to another thread pays later (measured idle on this
#: project's 2-core machine, best of 300: 260 k, the n = 1000 corner's M times the 4
#: residual probes, 0.23 ms on one thread against 0.47 ms on two; 420 k, the
#: 5120-patch Cornell box's M times a vector, 0.62 against 0.69 ms; at 1.7 M they tie,
#: 0.84 ms).
SPMM_MIN_PARALLEL_WORK = 1_000_000
#: spgemm emits a row by scanning its column span [lo, hi] of the dense accumulator
#: (no sort) when span <= ratio * (multiply-adds of the row); otherwise it sorts the
#: list of touched columns.
SPGEMM_DENSE_SCAN_RATIO = 4.0
#: Threads streaming tile rows of X (or T) against one frame batch: reading one tile
#: row overlaps the product of another.
COMPENSATE_WORKERS = 2
#: Series terms n of the matrix-free path when neither the user nor X's metadata says.
DEFAULT_COMPENSATION_TERMS = 4

# --- scenes ---------------------------------------------------------------------------
#: Rows of the form-factor matrix whose candidate pairs are enumerated at once. The
#: candidate arrays of one chunk bound the memory of the form factors: at 2048 the
#: 96x128 hemispheres peaked at 2.9 GB (31 s), at 512 at 0.84 GB (22 s); the dense
#: 384x512 corner takes 20 s either way.
SCENE_PAIR_CHUNK = 512
#: A scene's form-factor matrix may hold at most this many entries (float64 + int32:
#: ~12 bytes each, times ~3 while it is assembled).
SCENE_MAX_A_NNZ = 150_000_000
#: Scenes up to this many pixels are exact by default (no cut, no truncation: T is then
#: dense, n^2 entries, and each bounce a dense product).
SCENE_EXACT_MAX_N = 1024
#: With no form-factor cut every pair is tested: refuse beyond this many pairs.
SCENE_MAX_ALL_PAIRS = 64_000_000
#: Relative margin of the ray-sphere occlusion test (an endpoint on a sphere is not a hit).
SCENE_VISIBILITY_MARGIN = 1e-7
#: Density presets of the scenes (form-factor cut, threshold on T). "sparse" keeps about
#: 20 entries per row of T, like a thresholded capture; "dense" several hundred (the
#: out-of-core benchmark). Calibrated on the 384x512 corner (albedo 0.6): sparse gives
#: A 8 and T ~20 entries per row, dense A 71 and T ~300 per row (about 60 M in all).
#: Entries of T scale as 1/n, so at smaller sizes the same values keep more per row.
SCENE_SPARSE_FF_CUT = 5e-4
SCENE_SPARSE_THRESHOLD = 1e-5
SCENE_DENSE_FF_CUT = 1e-4
SCENE_DENSE_THRESHOLD = 1e-7
#: Gaussian projector blur is truncated at this many standard deviations.
SCENE_BLUR_TRUNCATE = 3.0
#: Bounce terms R_k are pruned at this fraction of the T threshold (divided by max F).
SCENE_PRUNE_FRACTION = 0.1
#: With no threshold the bounce series stops when a bounce's largest T entry is below this.
SCENE_NEUMANN_TOL = 1e-12
#: A bounce series not converged after this many bounces is reported as divergent.
SCENE_MAX_BOUNCES = 200
#: A scene lists its bounces' shares of the light (sum(A^k F 1), adding up to 100 %) until
#: a bounce's norm is below this fraction of the first's, for at most
#: this many bounces.
SCENE_SHARE_TOL = 1e-4
SCENE_SHARE_MAX_BOUNCES = 30
#: Relative tolerance of the scenes' ground-truth spectral radii (ARPACK).
SCENE_SPECTRAL_RTOL = 1e-6
#: ...and gives up (the radius "undetermined", never a guess) after this many products
#: (each one streams T or A once when they do not fit SCENE_IN_MEMORY_BYTES).
SCENE_SPECTRAL_MAX_PRODUCTS = 600
#: Above this many unknowns (beyond full HD) a grey scene's rho(M) and rho(A) are
#: bracketed by Collatz-Wielandt bounds (rigorous, their half-width recorded as the
#: uncertainty) instead of ARPACK's tolerance: ARPACK's Krylov vectors take
#: SPECTRAL_RADIUS_NCV n float64 (1.3 GB at 4K, beyond a 4 GiB build's share) and its
#: ~600 products, each streaming T from disk, did not converge in 18 minutes on the 4K
#: corner; the bracket holds a handful of vectors and took ~20 products.
SCENE_BRACKET_MIN_N = 4_000_000
#: Share of a scene build's memory limit the ground truth's products may fill with
#: decoded tile rows of T or A (at most what the process does not hold already); the
#: rest holds the estimates' vectors (n float64 each) and the products' temporaries.
SCENE_STATS_CACHE_SHARE = 0.5
#: Share of the limit the ground truth's cache leaves free besides what the process
#: holds and the vectors: the products' temporaries and the estimates' work. Filling
#: the rest exactly put the 4K corner's build at 4.21 GiB under a 4 GiB limit.
SCENE_STATS_HEADROOM_SHARE = 0.1
#: Memory a scene build may hold of A and T (default of ``memory_limit``): a matrix
#: within it is read whole once, a larger one tile row by tile row.
SCENE_IN_MEMORY_BYTES = 2 << 30
#: Bytes of decoded tiles of X (or T) that compensation keeps between frame batches;
#: beyond it tiles are re-read from disk on every pass (0: always re-read).
COMPENSATE_CACHE_BYTES = 1 << 30
#: spgemm multiplies rows of A in groups of 8 sharing one pass over B when, in a group,
#: useful multiply-adds / (8 x multiply-adds over the union of their columns) is at
#: least this (the other lanes multiply zeros); otherwise row by row.
SPGEMM_GROUP_MIN_EFFICIENCY = 0.25

# --- memory plan of a series run (bigT.schedule.memory) ---
#: Kept free under a memory_limit for what is not budgeted: allocator fragmentation,
#: zarr's encode buffers, dask's bookkeeping.
MEMORY_HEADROOM_BYTES = 128 << 20
#: The least a task may work in (a batch of the right factor and partial sums).
MEMORY_MIN_WORK_BYTES = 24 << 20
#: Of what is left after the baseline, headroom and fixed per-task parts: the tile
#: cache's share and the shared right factor's share; the rest goes to the tasks.
MEMORY_CACHE_SHARE = 0.35
MEMORY_WHOLE_SHARE = 0.35

# --- acquisition (bigT.acquisition) ------------------------------------------------
#: A camera pixel belongs to the projector super-pixel with its largest response only
#: when that response is at least this share of what it receives under an all-white
#: pattern: pixels lit by interreflection alone (no super-pixel dominates) are left out.
ACQUIRE_MIN_DIRECT_SHARE = 0.2
#: Default noise floor of T's entries, in units of the noise of one camera super-pixel
#: (the black capture's robust pixel noise x sqrt(2 / mean group size): the black
#: capture's own noise is in every signal).
ACQUIRE_FLOOR_SIGMAS = 3.0
#: Memory for the entries of T gathered at once (a pass over the captures fills the
#: tile rows that fit; more passes when they do not).
ACQUIRE_MEMORY_BYTES = 1 << 30

# --- real-time compensation (bigT.compensation.resident, bigT.compensation.realtime) ---
#: Share of the available memory (MemAvailable) that X may take when compensation
#: holds it in memory; beyond it X is streamed tile row by tile row (``--memory-limit``
#: overrides the budget).
COMPENSATE_RESIDENT_FRACTION = 0.5
#: The budget where the available memory cannot be read.
COMPENSATE_RESIDENT_FALLBACK_BYTES = 1 << 30
#: Batches decoded ahead of the one being compensated, and written behind it, by the
#: reader and writer threads of a frame stream. One keeps the reader busy while the
#: products run; more only makes frames of a file wait longer (latency), not faster.
COMPENSATE_QUEUE_DEPTH = 1

#: Delete a superseded term's directory in a background thread (after its atomic rename
#: to a hidden ``.trash`` sibling): deleting thousands of tile files waits on the file
#: system (measured: 2707 entries in 0.3-3.4 s), time the next term's products can use.
#: The engine waits for these deletions before it returns; meanwhile the disk holds
#: the dropped term too (set False when the disk is nearly full).
BACKGROUND_REMOVAL = True

#: What a power cut (or a kernel crash) may not undo of a store being written
#: (bigT.storage.replace.durable): "full" fsyncs every file before the rename that publishes it
#: (a tile row's chunks before its marker, a store's index before its completion flag)
#: and the directory after, so a row marked complete, a finished store or a published
#: term is on disk whole, as SQLite and LMDB order their writes; "none" skips the
#: fsyncs (a killed process still leaves every store whole or resumable, a power cut
#: may not), for scratch stores on a disk where the fsyncs cost. Measured (4 terms,
#: ext4 on a virtual disk, best of 3): the dense 96x128 corner's inverse 5.9 s -> 7.4 s
#: (+26 %, 8372 fsyncs), the sparse 384x512 corner's 3.8 s -> 4.5 s (+18 %, 10908).
DURABILITY = "full"
DURABILITY_LEVELS = ("none", "full")

#: Object storage (issue #31): a writer's lock object is a lease, renewed every quarter
#: of this many seconds while the writer lives; one not renewed for this long is
#: abandoned (its writer killed, its machine lost) and the next writer takes it over.
#: A bucket has no flock that dies with its process.
OBJECT_LOCK_SECONDS = 120.0

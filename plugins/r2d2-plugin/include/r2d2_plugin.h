/*
 * r2d2_plugin.h: the C ABI between the r2d2 imaging engine (the host) and a native
 * network-step plugin, a shared library named in a pipeline as
 *
 *     step: {kind: native, library: path/to/libmine.so, iterations: 10, config: {...}, to: update}
 *
 * ABI version 1. Any change to a signature, a struct layout or a rule below bumps
 * R2D2_PLUGIN_ABI_VERSION; the host refuses a library whose version differs from its own.
 *
 * What a plugin computes. At iteration i (1-based) of the imaging loop the host gives the
 * previous estimate x_{i-1} ("model", Jy/pixel), its residual dirty image
 * r_{i-1} = x_d - D x_{i-1} (Jy/beam), the dirty image x_d and the PSF over twice the field;
 * the plugin writes an increment. The host then forms
 *     x_i = max(0, x_{i-1} + increment)     (positivity: true, the default, as R2D2)
 *     x_i =        x_{i-1} + increment      (positivity: false)
 * and the residual update computes r_i. x_0 = 0 and r_0 = x_d.
 *
 * Images. Row-major N x N arrays of double, pixel (ix, iy) 0-based at index iy * N + ix,
 * which is FITS storage order (axis 1, RA, runs fastest); the phase centre is (N/2, N/2).
 * The PSF has peak 1 at (N/2, N/2) in the N x N field; psf_2n is the same PSF over a 2N x 2N
 * field with its peak at (N, N), i.e. index N * 2N + N: D x is the linear convolution of x
 * with it (crop(IFFT(FFT(pad(x)) FFT(psf_2n))), so a plugin can compute D itself).
 *
 * Symbols. A plugin exports exactly these five functions with C linkage (see below); the
 * host looks up r2d2_plugin_abi_version first and refuses the library before touching the
 * others when the version differs.
 *
 * Errors. No function may let an exception, a Rust panic or a longjmp escape: catch it and
 * report it as an error (the Rust support crate does this for you). Failures are reported by
 * a NULL handle (create) or a non-zero return (step); the message is then read with
 * r2d2_plugin_last_error. Messages are NUL-terminated UTF-8 (invalid bytes are shown
 * replaced), for a human: say what was wrong and what was expected.
 *
 * Threads. The host may create several handles from one library (one per pipeline stage)
 * and use them concurrently from different threads, so global state must be thread-safe.
 * One handle is used by one thread at a time, but not always the same thread: it is created
 * while the pipeline is built and stepped on the stage's thread. A plugin may run its own
 * threads inside a call, and must have stopped using the caller's buffers when it returns.
 *
 * Lifetime. The host keeps the library loaded until every handle is destroyed. Every
 * non-NULL handle returned by create is passed to destroy exactly once, and to nothing after.
 */
#ifndef R2D2_PLUGIN_H
#define R2D2_PLUGIN_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* The version of this contract. A plugin returns it from r2d2_plugin_abi_version. */
#define R2D2_PLUGIN_ABI_VERSION 1u

/* Export marker for the five functions (default visibility with GCC/Clang, dllexport on Windows). */
#if defined(_WIN32)
#define R2D2_PLUGIN_EXPORT __declspec(dllexport)
#else
#define R2D2_PLUGIN_EXPORT __attribute__((visibility("default")))
#endif

/*
 * The inputs of one step. Every pointer is valid, non-NULL and read-only for the duration
 * of the call only: copy what you need to keep. None of them overlaps increment_out.
 * (Two 64-bit integers first, then pointers: the layout has no padding on any platform.)
 */
typedef struct r2d2_step_input {
    uint64_t size;          /* N: images are N x N */
    uint64_t iteration;     /* i, 1-based; at most the series length (`iterations:`) */
    const double *residual; /* r_{i-1}, N x N, Jy/beam */
    const double *model;    /* x_{i-1}, N x N, Jy/pixel (all zero at i = 1) */
    const double *dirty;    /* x_d, N x N, Jy/beam */
    const double *psf_2n;   /* 2N x 2N, peak at (N, N) */
} r2d2_step_input;

/* Returns R2D2_PLUGIN_ABI_VERSION as the plugin was compiled. Must not fail. */
R2D2_PLUGIN_EXPORT uint32_t r2d2_plugin_abi_version(void);

/*
 * Creates a plugin instance, while the pipeline is built and before any imaging, so that a
 * bad configuration fails early: check everything here (and load model files, allocate).
 *   config_json  the stage's `config:` mapping as a NUL-terminated UTF-8 JSON object
 *                ("{}" when absent); valid for the duration of the call only.
 *   image_size   N, the pipeline's image size: reject a size the plugin cannot handle.
 *   iterations   the series length the pipeline will run (`iterations:`), >= 1.
 * Returns an opaque handle, or NULL on failure; the message is then
 * r2d2_plugin_last_error(NULL), read by the host on the same thread right after the call.
 */
R2D2_PLUGIN_EXPORT void *r2d2_plugin_create(const char *config_json, uint64_t image_size, uint32_t iterations);

/*
 * One network step: writes the increment for every one of the N x N pixels of
 * increment_out (host-owned, writable, N * N doubles; its contents on entry are unspecified:
 * the host fills it with NaN so that an unwritten pixel is caught). Every value written must
 * be finite. Returns 0 on success, non-zero on failure (message: r2d2_plugin_last_error(handle)).
 */
R2D2_PLUGIN_EXPORT int32_t r2d2_plugin_step(void *handle, const r2d2_step_input *input, double *increment_out);

/*
 * The message of the last failure: of the last step on `handle` when handle is non-NULL, or
 * of the last failed create on the calling thread when handle is NULL. Never NULL (an empty
 * string when there was no failure). The string belongs to the plugin and stays valid until
 * the next call with the same handle (or, for NULL, the next create on that thread).
 */
R2D2_PLUGIN_EXPORT const char *r2d2_plugin_last_error(const void *handle);

/* Releases a handle and everything it owns. NULL is ignored. */
R2D2_PLUGIN_EXPORT void r2d2_plugin_destroy(void *handle);

#ifdef __cplusplus
}
#endif

#endif /* R2D2_PLUGIN_H */

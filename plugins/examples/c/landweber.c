/*
 * The Landweber example plugin in C, against r2d2_plugin.h: increment = gain * residual.
 * Its configuration is {"gain": <number>}; a real plugin would use a JSON library, this one
 * reads the single number with strtod to stay dependency-free.
 *
 *   cc -O2 -shared -fPIC -I plugins/r2d2-plugin/include plugins/examples/c/landweber.c -o libc_landweber.so
 */
#include "r2d2_plugin.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    double gain;
    char last_error[256];
} landweber;

/* A failed create has no handle to keep its message: one per thread, as the header asks. */
static _Thread_local char create_error[256];

uint32_t r2d2_plugin_abi_version(void) { return R2D2_PLUGIN_ABI_VERSION; }

void *r2d2_plugin_create(const char *config_json, uint64_t image_size, uint32_t iterations) {
    (void)image_size;
    (void)iterations;
    create_error[0] = '\0';
    const char *key = config_json ? strstr(config_json, "\"gain\"") : NULL;
    const char *colon = key ? strchr(key, ':') : NULL;
    char *end = NULL;
    double gain = colon ? strtod(colon + 1, &end) : NAN;
    if (!colon || end == colon + 1 || !isfinite(gain) || gain <= 0.0) {
        snprintf(create_error, sizeof create_error, "config.gain: expected a positive number in %s",
                 config_json ? config_json : "(NULL)");
        return NULL;
    }
    landweber *self = calloc(1, sizeof *self);
    if (!self) {
        snprintf(create_error, sizeof create_error, "out of memory");
        return NULL;
    }
    self->gain = gain;
    return self;
}

int32_t r2d2_plugin_step(void *handle, const r2d2_step_input *input, double *increment_out) {
    landweber *self = handle;
    uint64_t pixels = input->size * input->size;
    for (uint64_t k = 0; k < pixels; k++) increment_out[k] = self->gain * input->residual[k];
    self->last_error[0] = '\0';
    return 0;
}

const char *r2d2_plugin_last_error(const void *handle) {
    return handle ? ((const landweber *)handle)->last_error : create_error;
}

void r2d2_plugin_destroy(void *handle) { free(handle); }

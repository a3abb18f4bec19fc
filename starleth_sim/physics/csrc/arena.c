/* The kernels' arena: work arrays carved from one block instead of malloc'd one by one (see
 * core.h). A request that does not fit is served by malloc, kept on a list freed at the next
 * reset, and counted; the block then grows to what the last use wanted, so that a steady
 * loop allocates nothing after its first steps. */
#include "core.h"

#include <stdlib.h>
#include <string.h>
#include <time.h>

#define ARENA_ALIGN 64

struct arena_chunk {
    arena_chunk *next;
    void *memory; /* as malloc returned it (data is aligned inside) */
};

static size_t round_up(size_t n) {
    return (n + ARENA_ALIGN - 1) / ARENA_ALIGN * ARENA_ALIGN;
}

static void *aligned_block(size_t n, void **memory) {
    char *p = malloc(n + ARENA_ALIGN);
    *memory = p;
    if (!p) return NULL;
    return p + (ARENA_ALIGN - (uintptr_t)p % ARENA_ALIGN) % ARENA_ALIGN;
}

void arena_init(arena_t *a, size_t cap) {
    memset(a, 0, sizeof(*a));
    if (cap) {
        a->base = malloc(round_up(cap) + ARENA_ALIGN);
        if (a->base) a->cap = round_up(cap);
    }
}

static void free_extra(arena_t *a) {
    arena_chunk *c = a->extra;
    while (c) {
        arena_chunk *next = c->next;
        free(c->memory);
        free(c);
        c = next;
    }
    a->extra = NULL;
}

void arena_free(arena_t *a) {
    free_extra(a);
    free(a->base);
    memset(a, 0, sizeof(*a));
}

void arena_reset(arena_t *a) {
    if (a->extra) free_extra(a);
    if (a->wanted > a->cap) { /* grow to what the last use wanted (with some room) */
        size_t cap = round_up(a->wanted + a->wanted / 4);
        char *p = malloc(cap + ARENA_ALIGN);
        if (p) {
            free(a->base);
            a->base = p;
            a->cap = cap;
        }
    }
    a->used = 0;
    a->wanted = 0;
}

void *arena_alloc(arena_t *a, size_t n) {
    size_t size = round_up(n ? n : 1);
    a->wanted += size;
    if (a->base) {
        char *start = a->base + (ARENA_ALIGN - (uintptr_t)a->base % ARENA_ALIGN) % ARENA_ALIGN;
        if (a->used + size <= a->cap) {
            void *p = start + a->used;
            a->used += size;
            return p;
        }
    }
    a->misses++;
    arena_chunk *c = malloc(sizeof(arena_chunk));
    void *p = c ? aligned_block(size, &c->memory) : NULL;
    if (!p) {
        free(c);
        if (a->oom) longjmp(*a->oom, 1);
        abort(); /* no entry point to report to: nothing else is safe */
    }
    c->next = a->extra;
    a->extra = c;
    return p;
}

static _Thread_local arena_t thread_arena;

arena_t *scratch_arena(void) {
    return &thread_arena;
}

double clock_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

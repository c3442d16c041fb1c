/*
 * Host harness for the firmware core: the core behind stdin/stdout, for tests (tests/test_firmware.py).
 *
 *   tr_host N_TAXELS ST_BLOCK PVDF_BLOCK RING_BYTES ENTROPY_SEED  < commands  > serial bytes
 *
 * Commands on stdin (binary, little-endian), one byte each then their operands:
 *   'P' u8 channel (1 SingleTact, 2 PVDF), u64 t_us, f32 value[N_TAXELS]  push one sample (N or V)
 *   'D'                                                                 the host reads: drain the ring to stdout
 *   'R' u32 n                                                           the host reads at most n bytes
 *   'F'                                                                 flush both channels' partial frames
 * At end of input both channels are flushed and the ring drained; the channels' counters go to
 * stderr as one JSON line. Samples pushed while no 'D' comes are what a stalled host means to the
 * device: the ring fills and whole frames are dropped.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "tr_fw.h"

static uint32_t entropy(void *ctx) { /* xorshift32 over the seed: deterministic for tests */
    uint32_t *s = ctx;
    *s ^= *s << 13;
    *s ^= *s >> 17;
    *s ^= *s << 5;
    return *s;
}

static int read_exact(uint8_t *p, size_t n) { return fread(p, 1, n, stdin) == n; }

static uint64_t get_le(const uint8_t *p, int n) {
    uint64_t v = 0;
    for (int i = n - 1; i >= 0; i--) v = (v << 8) | p[i];
    return v;
}

/* Send at most `limit` bytes from the ring to stdout, as a link would. */
static void drain(tr_ring_t *ring, uint32_t limit) {
    const uint8_t *data;
    uint32_t n;
    while (limit > 0 && (n = tr_ring_peek(ring, &data)) > 0) {
        if (n > limit) n = limit;
        fwrite(data, 1, n, stdout);
        tr_ring_consume(ring, n);
        limit -= n;
    }
}

static int fail(const char *msg) {
    fprintf(stderr, "tr_host: %s\n", msg);
    return 2;
}

static void print_stats(const tr_device_t *dev) {
    const tr_channel_id chans[2] = {TR_SINGLETACT, TR_PVDF};
    const char *names[2] = {"singletact", "pvdf"};
    fprintf(stderr, "{\"session\": %u", dev->session);
    for (int i = 0; i < 2; i++) {
        const tr_channel_stats_t *s = tr_stats(dev, chans[i]);
        fprintf(stderr, ", \"%s\": {\"frames_sent\": %lu, \"frames_dropped\": %lu, \"samples\": %lu, \"breaks\": %lu, \"rejected\": %lu}",
                names[i], (unsigned long)s->frames_sent, (unsigned long)s->frames_dropped, (unsigned long)s->samples,
                (unsigned long)s->breaks, (unsigned long)s->rejected);
    }
    fprintf(stderr, "}\n");
}

static tr_device_t dev;
static uint8_t ring_storage[1u << 20];

int main(int argc, char **argv) {
    if (argc != 6) return fail("usage: tr_host N_TAXELS ST_BLOCK PVDF_BLOCK RING_BYTES ENTROPY_SEED");
    unsigned long n_taxels = strtoul(argv[1], NULL, 10), st_block = strtoul(argv[2], NULL, 10);
    unsigned long pvdf_block = strtoul(argv[3], NULL, 10), ring_bytes = strtoul(argv[4], NULL, 10);
    uint32_t seed = (uint32_t)strtoul(argv[5], NULL, 10) | 1u;
    tr_ring_t ring;
    if (ring_bytes > sizeof ring_storage || tr_ring_init(&ring, ring_storage, (uint32_t)ring_bytes) != TR_OK)
        return fail("RING_BYTES must be a power of two up to 1 MiB");
    if (n_taxels > TR_MAX_TAXELS || st_block > 0xFFFF || pvdf_block > 0xFFFF ||
        tr_device_init(&dev, (uint16_t)n_taxels, (uint16_t)st_block, (uint16_t)pvdf_block, &ring, entropy, &seed) != TR_OK)
        return fail("bad sizes: 1..256 taxels, taxels * block <= 1024, ring >= one frame");
    float values[TR_MAX_TAXELS];
    uint8_t head[9], raw[4 * TR_MAX_TAXELS];
    int cmd;
    while ((cmd = getchar()) != EOF) {
        if (cmd == 'P') {
            if (!read_exact(head, sizeof head) || !read_exact(raw, 4 * n_taxels)) return fail("truncated sample");
            for (unsigned long i = 0; i < n_taxels; i++) {
                uint32_t bits = (uint32_t)get_le(raw + 4 * i, 4);
                float f;
                memcpy(&f, &bits, sizeof f);
                values[i] = f;
            }
            if (head[0] != TR_SINGLETACT && head[0] != TR_PVDF) return fail("bad channel");
            tr_push(&dev, (tr_channel_id)head[0], get_le(head + 1, 8), values); /* refusals are counted */
        } else if (cmd == 'D') {
            drain(&ring, UINT32_MAX);
        } else if (cmd == 'R') {
            if (!read_exact(head, 4)) return fail("truncated read");
            drain(&ring, (uint32_t)get_le(head, 4));
        } else if (cmd == 'F') {
            tr_flush(&dev, TR_SINGLETACT);
            tr_flush(&dev, TR_PVDF);
        } else {
            return fail("unknown command");
        }
    }
    tr_flush(&dev, TR_SINGLETACT);
    tr_flush(&dev, TR_PVDF);
    drain(&ring, UINT32_MAX);
    fflush(stdout);
    print_stats(&dev);
    return 0;
}

/* TouchReal sensor firmware core: framing, CRCs, sequence numbers, device clock, TX ring (tr_fw.h). */
#include "tr_fw.h"

#include <string.h>

/* Compiler barrier: the ring's data is written before the index that publishes it. A single-core
 * Cortex-M does not reorder its own stores as seen by its interrupts, so this is enough there. */
#if defined(__GNUC__)
#define TR_BARRIER() __asm__ volatile("" ::: "memory")
#else
#define TR_BARRIER() ((void)0)
#endif

/* CRCs four bits at a time: 16-entry tables (96 bytes of flash), two steps per byte instead of eight
 * (1.7x the bitwise loop on the x86 host; not measured on a Cortex-M4). */
static const uint16_t crc16_nibble[16] = {
    0x0000u, 0x1021u, 0x2042u, 0x3063u, 0x4084u, 0x50A5u, 0x60C6u, 0x70E7u,
    0x8108u, 0x9129u, 0xA14Au, 0xB16Bu, 0xC18Cu, 0xD1ADu, 0xE1CEu, 0xF1EFu,
};
static const uint32_t crc32_nibble[16] = {
    0x00000000u, 0x1DB71064u, 0x3B6E20C8u, 0x26D930ACu, 0x76DC4190u, 0x6B6B51F4u, 0x4DB26158u, 0x5005713Cu,
    0xEDB88320u, 0xF00F9344u, 0xD6D6A3E8u, 0xCB61B38Cu, 0x9B64C2B0u, 0x86D3D2D4u, 0xA00AE278u, 0xBDBDF21Cu,
};

uint16_t tr_crc16(const uint8_t *p, size_t n) {
    uint16_t crc = 0xFFFFu;
    while (n--) {
        crc ^= (uint16_t)(*p++ << 8);
        crc = (uint16_t)((crc << 4) ^ crc16_nibble[crc >> 12]);
        crc = (uint16_t)((crc << 4) ^ crc16_nibble[crc >> 12]);
    }
    return crc;
}

uint32_t tr_crc32(const uint8_t *p, size_t n) {
    uint32_t crc = 0xFFFFFFFFu;
    while (n--) {
        crc ^= *p++;
        crc = (crc >> 4) ^ crc32_nibble[crc & 0xFu];
        crc = (crc >> 4) ^ crc32_nibble[crc & 0xFu];
    }
    return ~crc;
}

float tr_nan(void) {
    const uint32_t bits = 0x7FC00000u;
    float f;
    memcpy(&f, &bits, sizeof f);
    return f;
}

/* ---- little-endian stores, independent of the CPU's byte order ------------------------------ */

static void put_u16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v) {
    for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static void put_u64(uint8_t *p, uint64_t v) {
    for (int i = 0; i < 8; i++) p[i] = (uint8_t)(v >> (8 * i));
}

static void put_f32(uint8_t *p, float f) {
    uint32_t bits;
    memcpy(&bits, &f, sizeof bits);
    put_u32(p, bits);
}

/* ---- device clock --------------------------------------------------------------------------- */

void tr_clock_init(tr_clock_t *clk, uint32_t raw_us) {
    clk->now_us = 0;
    clk->last_raw = raw_us;
}

uint64_t tr_clock_now(tr_clock_t *clk, uint32_t raw_us) {
    clk->now_us += (uint32_t)(raw_us - clk->last_raw); /* modulo 2^32: one wrap is absorbed */
    clk->last_raw = raw_us;
    return clk->now_us;
}

/* ---- ring ----------------------------------------------------------------------------------- */

tr_status tr_ring_init(tr_ring_t *r, uint8_t *storage, uint32_t capacity) {
    if (r == NULL || storage == NULL || capacity == 0 || (capacity & (capacity - 1u)) != 0) return TR_EINVAL;
    r->buf = storage;
    r->mask = capacity - 1u;
    r->head = 0;
    r->tail = 0;
    return TR_OK;
}

uint32_t tr_ring_used(const tr_ring_t *r) { return r->head - r->tail; }

bool tr_ring_has_room(const tr_ring_t *r, uint32_t n) { return n <= r->mask + 1u - tr_ring_used(r); }

uint32_t tr_ring_peek(const tr_ring_t *r, const uint8_t **data) {
    uint32_t tail = r->tail, used = r->head - tail, start = tail & r->mask;
    uint32_t run = r->mask + 1u - start;
    TR_BARRIER(); /* the bytes are read after the index that published them */
    *data = r->buf + start;
    return used < run ? used : run;
}

void tr_ring_consume(tr_ring_t *r, uint32_t n) {
    TR_BARRIER();
    r->tail += n;
}

/* Copy n bytes in (the caller checked the room) and publish them. */
static void ring_write(tr_ring_t *r, const uint8_t *p, uint32_t n) {
    uint32_t head = r->head, start = head & r->mask, first = r->mask + 1u - start;
    if (first > n) first = n;
    memcpy(r->buf + start, p, first);
    memcpy(r->buf, p + first, n - first);
    TR_BARRIER();
    r->head = head + n;
}

/* ---- framer --------------------------------------------------------------------------------- */

uint16_t tr_pvdf_block_for(uint16_t n_taxels) {
    if (n_taxels < 1 || n_taxels > TR_MAX_TAXELS) return 0;
    uint16_t fit = (uint16_t)(TR_MAX_VALUES / n_taxels);
    return fit < TR_PVDF_BLOCK ? fit : (uint16_t)TR_PVDF_BLOCK;
}

static void framer_init(tr_framer_t *f, tr_channel_id id, uint16_t block, uint32_t period_us) {
    memset(f, 0, sizeof *f);
    f->id = (uint8_t)id;
    f->block = block;
    f->period_us = period_us;
}

/* splitmix64's finaliser: spreads weak entropy over all bits. */
static uint64_t mix64(uint64_t z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

tr_status tr_device_init(tr_device_t *dev, uint16_t n_taxels, uint16_t st_block, uint16_t pvdf_block,
                         tr_ring_t *ring, tr_entropy_fn entropy, void *entropy_ctx) {
    if (dev == NULL || ring == NULL || entropy == NULL || n_taxels < 1 || n_taxels > TR_MAX_TAXELS || st_block < 1 ||
        pvdf_block < 1 || (uint32_t)n_taxels * st_block > TR_MAX_VALUES ||
        (uint32_t)n_taxels * pvdf_block > TR_MAX_VALUES ||
        !tr_ring_has_room(ring, TR_FRAME_SIZE((uint32_t)n_taxels * (st_block > pvdf_block ? st_block : pvdf_block))))
        return TR_EINVAL;
    uint64_t seed = 0;
    for (int i = 0; i < 8; i++) seed = mix64(seed ^ entropy(entropy_ctx));
    dev->n_taxels = n_taxels;
    dev->session = (uint16_t)(seed >> 48);
    dev->ring = ring;
    framer_init(&dev->st, TR_SINGLETACT, st_block, TR_ST_PERIOD_US);
    framer_init(&dev->pvdf, TR_PVDF, pvdf_block, TR_PVDF_PERIOD_US);
    return TR_OK;
}

static tr_framer_t *framer(tr_device_t *dev, tr_channel_id ch) {
    return ch == TR_SINGLETACT ? &dev->st : ch == TR_PVDF ? &dev->pvdf : NULL;
}

/* Finish the header and CRCs of the filled frame, queue it or drop it; the sequence number is used either way. */
static void emit(tr_device_t *dev, tr_framer_t *f) {
    uint8_t *p = f->frame;
    uint16_t seq = f->seq++, n_samples = f->filled; /* seq wraps 65535 -> 0 */
    uint32_t size = TR_FRAME_SIZE((uint32_t)n_samples * dev->n_taxels);
    f->filled = 0;
    if (!tr_ring_has_room(dev->ring, size)) { /* the host is not reading: no CRC work for a lost frame */
        f->stats.frames_dropped++;
        return;
    }
    p[0] = 0xA5;
    p[1] = 0x5A;
    p[2] = TR_VERSION;
    p[3] = f->id;
    put_u16(p + 4, seq);
    put_u16(p + 6, dev->session);
    put_u64(p + 8, f->t0_us);
    put_u16(p + 16, dev->n_taxels);
    put_u16(p + 18, n_samples);
    put_u16(p + 20, tr_crc16(p, 20));
    put_u32(p + size - TR_CRC_SIZE, tr_crc32(p, size - TR_CRC_SIZE));
    ring_write(dev->ring, p, size);
    f->stats.frames_sent++;
}

tr_status tr_push(tr_device_t *dev, tr_channel_id ch, uint64_t t_us, const float *values) {
    tr_framer_t *f = dev != NULL ? framer(dev, ch) : NULL;
    if (f == NULL || values == NULL) return TR_EINVAL;
    if (f->started && t_us <= f->last_us) {
        f->stats.rejected++;
        return TR_EINVAL;
    }
    f->started = true;
    f->last_us = t_us;
    if (f->filled > 0) {
        uint64_t expected = f->t0_us + (uint64_t)f->filled * f->period_us;
        uint64_t off = t_us > expected ? t_us - expected : expected - t_us;
        if (off > f->period_us / 2) {
            emit(dev, f);
            f->stats.breaks++;
        }
    }
    if (f->filled == 0) f->t0_us = t_us;
    uint8_t *p = f->frame + TR_HEADER_SIZE + 4u * (uint32_t)f->filled * dev->n_taxels;
    for (uint16_t i = 0; i < dev->n_taxels; i++) put_f32(p + 4u * i, values[i]);
    f->filled++;
    f->stats.samples++;
    if (f->filled == f->block) emit(dev, f);
    return TR_OK;
}

tr_status tr_flush(tr_device_t *dev, tr_channel_id ch) {
    tr_framer_t *f = dev != NULL ? framer(dev, ch) : NULL;
    if (f == NULL) return TR_EINVAL;
    if (f->filled > 0) emit(dev, f);
    return TR_OK;
}

const tr_channel_stats_t *tr_stats(const tr_device_t *dev, tr_channel_id ch) {
    return ch == TR_SINGLETACT ? &dev->st.stats : ch == TR_PVDF ? &dev->pvdf.stats : NULL;
}

/*
 * TouchReal sensor firmware core: portable C99, no dynamic memory, no OS.
 *
 * It turns samples into the serial frames of docs/serial-protocol.md (version 1):
 *   - SingleTact force, newtons (N), one sample per taxel every TR_ST_PERIOD_US (10 000 us, 100 Hz);
 *   - PVDF film voltage, volts (V) around the bias, one sample per taxel every TR_PVDF_PERIOD_US
 *     (500 us, 2 kHz).
 * Each channel packs its own frames (per-channel u16 sequence numbers, 22-byte header with a
 * CRC-16/CCITT-FALSE, float32 samples, CRC-32 trailer) and hands each finished frame to a bounded
 * byte ring that the link (UART, USB CDC) drains. When the ring has no room for a whole frame the
 * frame is dropped but its sequence number is used, so the host sees a gap, never a torn frame.
 *
 * Times are integer microseconds of a monotonic 64-bit device clock (tr_clock_t extends a
 * free-running 32-bit microsecond counter). A failed reading is reported as NaN (tr_nan()).
 *
 * Concurrency: one producer (the sampling interrupt calling tr_push / tr_flush) and one consumer
 * (the link calling tr_ring_peek / tr_ring_consume) may run in different contexts; the ring's
 * indices are each written by one side only. Two producers on the same tr_device_t need a lock.
 */
#ifndef TR_FW_H
#define TR_FW_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define TR_VERSION 1
#define TR_HEADER_SIZE 22u                 /* bytes, including the header CRC-16 */
#define TR_CRC_SIZE 4u                     /* bytes of the trailing CRC-32 */
#define TR_MAX_TAXELS 256u
#define TR_MAX_VALUES 1024u                /* n_taxels * n_samples of one frame */
#define TR_FRAME_SIZE(n_values) (TR_HEADER_SIZE + 4u * (n_values) + TR_CRC_SIZE)
#define TR_MAX_FRAME_SIZE TR_FRAME_SIZE(TR_MAX_VALUES)   /* 4122 bytes */

#define TR_ST_PERIOD_US 10000u             /* SingleTact sample period, us (100 Hz) */
#define TR_PVDF_PERIOD_US 500u             /* PVDF sample period, us (2 kHz) */
#define TR_ST_BLOCK 1u                     /* recommended SingleTact samples per frame (10 ms) */
#define TR_PVDF_BLOCK 10u                  /* recommended PVDF samples per frame (5 ms) */

typedef enum { TR_SINGLETACT = 1, TR_PVDF = 2 } tr_channel_id;

typedef enum {
    TR_OK = 0,
    TR_EINVAL = -1,                        /* bad argument: sizes, channel, NULL */
} tr_status;

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor; "123456789" -> 0x29B1). */
uint16_t tr_crc16(const uint8_t *p, size_t n);
/* CRC-32 as zlib (reflected poly 0xEDB88320, init and final xor 0xFFFFFFFF; "123456789" -> 0xCBF43926). */
uint32_t tr_crc32(const uint8_t *p, size_t n);

/* A quiet NaN: the value of a failed reading. */
float tr_nan(void);

/* ---- device clock -------------------------------------------------------------------------- */

/* Extends a free-running 32-bit microsecond counter (wrapping every 71.6 min) to 64 bits.
 * tr_clock_now must be called at least once per wrap period; calls need not be periodic. */
typedef struct {
    uint64_t now_us;                       /* device time of the last call, us */
    uint32_t last_raw;                     /* counter value at the last call */
} tr_clock_t;

void tr_clock_init(tr_clock_t *clk, uint32_t raw_us);   /* device time starts at 0 */
uint64_t tr_clock_now(tr_clock_t *clk, uint32_t raw_us); /* monotonic device time, us */

/* ---- transmit ring ------------------------------------------------------------------------- */

/* Byte ring between the framer and the link; capacity is a power of two (>= one frame). */
typedef struct {
    uint8_t *buf;
    uint32_t mask;                         /* capacity - 1 */
    volatile uint32_t head;                /* bytes ever written (producer only) */
    volatile uint32_t tail;                /* bytes ever consumed (consumer only) */
} tr_ring_t;

tr_status tr_ring_init(tr_ring_t *r, uint8_t *storage, uint32_t capacity);
uint32_t tr_ring_used(const tr_ring_t *r);
bool tr_ring_has_room(const tr_ring_t *r, uint32_t n);   /* room for n more bytes? */
/* Longest contiguous run of unsent bytes at *data (for a DMA or a write call); 0 when empty. */
uint32_t tr_ring_peek(const tr_ring_t *r, const uint8_t **data);
void tr_ring_consume(tr_ring_t *r, uint32_t n);          /* n <= what tr_ring_peek returned */

/* ---- framer -------------------------------------------------------------------------------- */

typedef struct {
    uint32_t frames_sent;                  /* frames put in the ring */
    uint32_t frames_dropped;               /* frames dropped for lack of room (seq used) */
    uint32_t samples;                      /* samples pushed */
    uint32_t breaks;                       /* frames closed early: a sample off the period grid */
    uint32_t rejected;                     /* samples refused: not later than the channel's previous one */
} tr_channel_stats_t;

typedef struct {
    uint8_t id;                            /* tr_channel_id */
    uint16_t block;                        /* samples per frame */
    uint32_t period_us;
    uint16_t seq;                          /* number of the frame being filled */
    uint16_t filled;                       /* samples in it so far */
    uint64_t t0_us;                        /* device time of its first sample */
    uint64_t last_us;                      /* device time of the channel's latest sample */
    bool started;                          /* a sample was pushed since boot */
    tr_channel_stats_t stats;
    uint8_t frame[TR_MAX_FRAME_SIZE];      /* the frame being filled */
} tr_framer_t;

typedef struct {
    uint16_t n_taxels;
    uint16_t session;                      /* random per boot */
    tr_ring_t *ring;
    tr_framer_t st;                        /* TR_SINGLETACT */
    tr_framer_t pvdf;                      /* TR_PVDF */
} tr_device_t;

/* Caller-provided entropy: returns 32 random-ish bits (ADC noise LSBs, a unique ID, a timer...). */
typedef uint32_t (*tr_entropy_fn)(void *ctx);

/* Largest PVDF block <= TR_PVDF_BLOCK that fits TR_MAX_VALUES for n_taxels (0 if n_taxels is out of range). */
uint16_t tr_pvdf_block_for(uint16_t n_taxels);

/* Set up a device of n_taxels (1..256) with st_block / pvdf_block samples per frame
 * (n_taxels * block <= TR_MAX_VALUES; TR_ST_BLOCK and tr_pvdf_block_for() are the recommended
 * sizes). Sequence numbers start at 0; the session is drawn from `entropy` (8 calls, mixed). */
tr_status tr_device_init(tr_device_t *dev, uint16_t n_taxels, uint16_t st_block, uint16_t pvdf_block,
                         tr_ring_t *ring, tr_entropy_fn entropy, void *entropy_ctx);

/* Add one sample of channel `ch` for every taxel: values[n_taxels] in N (SingleTact) or V (PVDF),
 * NaN for a failed reading, taken at device time t_us. A sample that is not one period after the
 * previous one (more than half a period off) closes the current frame first, so the host's
 * t0_us + k * period is always the true sample time. A full frame goes to the ring (or is dropped).
 * A sample not later than the channel's previous one is refused (TR_EINVAL, counted in `rejected`):
 * the device clock of a session never runs backwards. */
tr_status tr_push(tr_device_t *dev, tr_channel_id ch, uint64_t t_us, const float *values);

/* Close channel ch's partial frame now (e.g. before sleeping); nothing happens when it is empty. */
tr_status tr_flush(tr_device_t *dev, tr_channel_id ch);

const tr_channel_stats_t *tr_stats(const tr_device_t *dev, tr_channel_id ch);

#endif /* TR_FW_H */

/*
 * SingleTact interface boards on I2C1 (standard mode, 100 kbit/s; PB6 SCL, PB7 SDA).
 *
 * Per the SingleTact manual: a Read Request (write 0x01, register offset, byte count, 0xFF) sets
 * what the next Read returns; the sensor results are registers 128..133 (frame index, timestamp,
 * output MSB, output LSB). The output is 10 bits (0..0x3FF); 0x100..0x2FF is the full-scale range.
 */
#include "board.h"

#include "config.h"
#include "regs.h"

#define ST_CMD_READ 0x01u
#define ST_RESULTS 128u                                       /* register offset of the results */
#define ST_RESULT_BYTES 6u

static const uint8_t addresses[] = ST_I2C_ADDRESSES;
_Static_assert(sizeof addresses >= TR_N_TAXELS, "one SingleTact address per taxel");

static void i2c_setup(void) {
    I2C1_CR1 = I2C_CR1_SWRST;
    I2C1_CR1 = 0;
    I2C1_CR2 = APB1_HZ / 1000000u;                            /* peripheral clock, MHz */
    I2C1_CCR = APB1_HZ / (2u * ST_I2C_HZ);                    /* standard mode, 50 % duty */
    I2C1_TRISE = APB1_HZ / 1000000u + 1u;                     /* 1000 ns maximum rise time */
    I2C1_CR1 = I2C_CR1_PE;
}

void singletact_init(void) {
    RCC_APB1ENR |= 1u << 21;                                  /* I2C1 */
    i2c_setup();
}

/* Wait until SR1 has `flag`; false on a bus error, a NACK or ST_I2C_TIMEOUT_US. */
static bool wait_sr1(uint32_t flag) {
    uint32_t start = board_micros();
    for (;;) {
        uint32_t sr1 = I2C1_SR1;
        if (sr1 & I2C_SR1_ERRORS) return false;
        if (sr1 & flag) return true;
        if (board_micros() - start > ST_I2C_TIMEOUT_US) return false;
    }
}

/* A (repeated) start and the address; waits for a previous STOP to go out first. */
static bool begin(uint8_t address, bool read) {
    uint32_t t0 = board_micros();
    while (I2C1_CR1 & I2C_CR1_STOP) {
        if (board_micros() - t0 > ST_I2C_TIMEOUT_US) return false;
    }
    I2C1_CR1 |= I2C_CR1_START | (read ? I2C_CR1_ACK : 0u);
    if (!wait_sr1(I2C_SR1_SB)) return false;
    I2C1_DR = (uint32_t)(address << 1) | (read ? 1u : 0u);
    if (!wait_sr1(I2C_SR1_ADDR)) return false;
    (void)I2C1_SR2;                                           /* SR1 then SR2 read: ADDR cleared */
    return true;
}

static bool write_bytes(uint8_t address, const uint8_t *p, uint32_t n) {
    if (!begin(address, false)) return false;
    for (uint32_t i = 0; i < n; i++) {
        if (!wait_sr1(I2C_SR1_TXE)) return false;
        I2C1_DR = p[i];
    }
    if (!wait_sr1(I2C_SR1_BTF)) return false;
    I2C1_CR1 |= I2C_CR1_STOP;
    return true;
}

/* Master receive of n >= 3 bytes, the reference manual's procedure for the last three. */
static bool read_bytes(uint8_t address, uint8_t *p, uint32_t n) {
    if (!begin(address, true)) return false;
    for (uint32_t i = 0; i + 3 < n; i++) {
        if (!wait_sr1(I2C_SR1_RXNE)) return false;
        p[i] = (uint8_t)I2C1_DR;
    }
    if (!wait_sr1(I2C_SR1_BTF)) return false;                 /* byte n-3 in DR, n-2 in the shift register */
    I2C1_CR1 &= ~I2C_CR1_ACK;
    p[n - 3] = (uint8_t)I2C1_DR;
    if (!wait_sr1(I2C_SR1_BTF)) return false;                 /* byte n-2 in DR, n-1 in (NACKed) */
    I2C1_CR1 |= I2C_CR1_STOP;
    p[n - 2] = (uint8_t)I2C1_DR;
    if (!wait_sr1(I2C_SR1_RXNE)) return false;
    p[n - 1] = (uint8_t)I2C1_DR;
    return true;
}

/* One sensor's force, N, or NaN; after a failure the bus is stopped and the peripheral reset. */
static float read_one(uint8_t address) {
    static const uint8_t request[] = {ST_CMD_READ, ST_RESULTS, ST_RESULT_BYTES, 0xFF};
    uint8_t r[ST_RESULT_BYTES];
    if (!write_bytes(address, request, sizeof request) || !read_bytes(address, r, sizeof r)) {
        I2C1_CR1 |= I2C_CR1_STOP;
        i2c_setup();
        return tr_nan();
    }
    uint32_t counts = ((uint32_t)r[4] << 8) | r[5];
    if (counts > 0x3FFu) return tr_nan();                     /* not a 10-bit output: a garbled transfer */
    return ((float)counts - ST_COUNTS_ZERO) * (ST_FULL_SCALE_N / ST_COUNTS_SPAN);
}

void singletact_read(float *newtons) {
    for (uint32_t i = 0; i < TR_N_TAXELS; i++) newtons[i] = read_one(addresses[i]);
}

/*
 * Every board and calibration constant of the Black Pill (STM32F411CEU6) target, in one place.
 * docs/hardware.md explains each one and how to measure it.
 */
#ifndef TR_BOARD_CONFIG_H
#define TR_BOARD_CONFIG_H

/* ---- taxels ---------------------------------------------------------------------------------- */
#ifndef TR_N_TAXELS
#define TR_N_TAXELS 1                      /* 1..8: PVDF of taxel i on PA<i> (ADC1_IN<i>) */
#endif
_Static_assert(TR_N_TAXELS >= 1 && TR_N_TAXELS <= 8, "the Black Pill target has 8 PVDF inputs, PA0..PA7");

/* ---- clocks ---------------------------------------------------------------------------------- */
#define HSE_HZ 25000000u                   /* the Black Pill's crystal */
#define SYSCLK_HZ 96000000u                /* PLL: 25 MHz / 25 * 192 / 2; USB clock 48 MHz (/4) */
#define APB1_HZ (SYSCLK_HZ / 2)            /* 48 MHz (I2C1); APB1 timers run at 96 MHz */
#define APB2_HZ SYSCLK_HZ                  /* 96 MHz (USART1, ADC1) */

/* ---- PVDF film through its charge amplifier, into the ADC (2 kHz per taxel) ------------------ */
#define PVDF_VOLTS_PER_COUNT (3.3f / 4095.0f)   /* 12-bit ADC on a 3.3 V reference */
#define PVDF_BIAS_COUNTS 2048.0f           /* the amplifier's mid-rail bias, counts (used if not measured) */
#define PVDF_BIAS_SAMPLES 2048u            /* samples averaged per taxel at boot to measure the bias (0: use PVDF_BIAS_COUNTS) */
#define PVDF_ADC_SAMPLE_CYCLES 4u          /* SMPR code 4 = 84 ADC cycles (3.5 us at 24 MHz): charge-amp output impedance */

/* ---- SingleTact over I2C (100 Hz per taxel) --------------------------------------------------- */
/* Interface boards answer at 0x04 as shipped; several on one bus each need their own address
 * (4..127, set with the SingleTact PC or Arduino tool) and 0x04 must then not be used. */
#define ST_I2C_ADDRESSES {0x04, 0x05, 0x06, 0x07, 0x08, 0x09, 0x0A, 0x0B}
#define ST_I2C_HZ 100000u                  /* the interface supports standard mode only */
#define ST_COUNTS_ZERO 256.0f              /* 0x100: output at no load (0.5 V analog) */
#define ST_COUNTS_SPAN 512.0f              /* 0x100..0x2FF: the sensor's full-scale range, 9 bits */
#define ST_FULL_SCALE_N 10.0f              /* full-scale force of the fitted sensor, N (8 mm, 10 N) */
#define ST_I2C_TIMEOUT_US 2000u            /* one transfer step; beyond it the reading is NaN */

/* ---- link to the host: USART1 (PA9 TX, PA10 RX, PA11 CTS) ------------------------------------ */
#define LINK_BAUD 921600u                  /* 92 kB/s: up to 9 taxels of frames (docs/serial-protocol.md) */
#define LINK_CTS 0                         /* 1: pause on the host's RTS (frames then drop as gaps, never tear) */
#define LINK_RING_BYTES 16384u             /* transmit ring, power of two: 0.2 s of 8 taxels */

#endif

/* Black Pill (STM32F411CEU6) drivers used by main.c: clock, microsecond timer, ADC, I2C, UART link. */
#ifndef TR_BOARD_H
#define TR_BOARD_H

#include <stdbool.h>
#include <stdint.h>

#include "tr_fw.h"

/* board.c: 96 MHz from the 25 MHz crystal, GPIO, TIM2 counting microseconds, interrupt helpers. */
void board_clock_init(void);
void board_gpio_init(void);
void board_timer_init(void);                          /* TIM2 free running at 1 MHz */
uint32_t board_micros(void);                          /* TIM2 counter, us (wraps every 71.6 min) */
void board_tick_start(uint32_t at_us);                /* first sampling interrupt (TIM2 compare) at at_us */
uint32_t board_tick_next(uint32_t period_us);         /* in that interrupt: ack it, schedule the next; its time, us */
void board_irq_enable(uint32_t irq, uint8_t priority);
void board_irq_disable(uint32_t irq);
void board_delay_us(uint32_t us);
void board_led_toggle(void);                         /* PC13, the on-board LED */

/* pvdf.c: ADC1 single conversions (PVDF on PA0..PA7, the temperature sensor for entropy). */
void pvdf_init(void);
uint16_t adc_read(uint32_t channel);                  /* one conversion, counts 0..4095 */
void pvdf_calibrate(void);                            /* measure each taxel's bias (film at rest) */
void pvdf_read(float *volts);                         /* one sample of every taxel, V around the bias */
uint32_t adc_entropy(void *ctx);                      /* tr_entropy_fn: ADC noise LSBs mixed with the chip's UID */

/* singletact.c: SingleTact interface boards on I2C1 (PB6 SCL, PB7 SDA). */
void singletact_init(void);
void singletact_read(float *newtons);                 /* every taxel's force, N; NaN where a read failed */

/* link.c: frames to the host over USART1 (PA9 TX) from the core's ring, interrupt driven. */
void link_init(tr_ring_t *ring);
void link_kick(void);                                 /* start sending if the ring has bytes */

#endif

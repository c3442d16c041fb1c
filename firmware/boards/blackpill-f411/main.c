/*
 * TouchReal sensor firmware for the WeAct Black Pill (STM32F411CEU6).
 *
 * TIM2 compare interrupts every TR_PVDF_PERIOD_US (500 us, 2 kHz) on an exact grid: each samples
 * every taxel's PVDF film through the ADC and pushes it to the core; every 20th also marks a
 * SingleTact sample due (100 Hz), which the main loop reads over I2C (about 1.2 ms per sensor, too
 * long for the interrupt) and pushes stamped with that tick's time. Frames leave through USART1.
 */
#include "board.h"
#include "config.h"

#define PRIO_SAMPLING 1u                                      /* TIM2 and USART1 share it: neither preempts the other */
#define ST_EVERY (TR_ST_PERIOD_US / TR_PVDF_PERIOD_US)        /* PVDF ticks per SingleTact sample */
#define IRQ_TIM2_N 28u
#define IRQ_USART1_N 37u

static tr_device_t dev;
static tr_ring_t ring;
static uint8_t ring_storage[LINK_RING_BYTES];
static tr_clock_t device_clock;
static volatile bool st_due;
static volatile uint64_t st_due_us;
static volatile uint32_t st_missed;                           /* SingleTact samples skipped: I2C too slow */
static uint32_t ticks;

void TIM2_IRQHandler(void) {
    uint64_t t_us = tr_clock_now(&device_clock, board_tick_next(TR_PVDF_PERIOD_US));
    float volts[TR_N_TAXELS];
    pvdf_read(volts);
    tr_push(&dev, TR_PVDF, t_us, volts);
    if (++ticks % ST_EVERY == 0) {
        if (st_due) st_missed++;
        st_due_us = t_us;
        st_due = true;
    }
    if (ticks % 2000u == 0) board_led_toggle();               /* 1 s heartbeat */
    link_kick();
}

int main(void) {
    board_clock_init();
    board_gpio_init();
    board_timer_init();
    pvdf_init();
    singletact_init();
    tr_ring_init(&ring, ring_storage, LINK_RING_BYTES);
    link_init(&ring);
    pvdf_calibrate();
    uint32_t entropy_round = 0;
    if (tr_device_init(&dev, TR_N_TAXELS, TR_ST_BLOCK, tr_pvdf_block_for(TR_N_TAXELS), &ring, adc_entropy,
                       &entropy_round) != TR_OK) {
        for (;;) board_led_toggle();                          /* a configuration error: LED dimly lit */
    }
    uint32_t first = board_micros() + 1000u;
    tr_clock_init(&device_clock, first);                      /* device time 0 = the first sample */
    board_tick_start(first);
    board_irq_enable(IRQ_USART1_N, PRIO_SAMPLING);
    board_irq_enable(IRQ_TIM2_N, PRIO_SAMPLING);
    for (;;) {
        if (!st_due) continue;
        board_irq_disable(IRQ_TIM2_N);                        /* a 64-bit read and the core have one producer at a time */
        uint64_t t_us = st_due_us;
        st_due = false;
        board_irq_enable(IRQ_TIM2_N, PRIO_SAMPLING);
        float newtons[TR_N_TAXELS];
        singletact_read(newtons);
        board_irq_disable(IRQ_TIM2_N);
        tr_push(&dev, TR_SINGLETACT, t_us, newtons);
        board_irq_enable(IRQ_TIM2_N, PRIO_SAMPLING);
        link_kick();
    }
}

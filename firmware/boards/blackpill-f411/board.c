/* Clock tree, GPIO, the microsecond timer and interrupt helpers of the Black Pill (RM0383). */
#include "board.h"

#include "config.h"
#include "regs.h"

void board_clock_init(void) {
    RCC_APB1ENR |= 1u << 28;                                  /* PWR */
    PWR_CR = (PWR_CR & ~(3u << 14)) | (3u << 14);             /* voltage scale 1: up to 100 MHz */
    RCC_CR |= RCC_CR_HSEON;
    while (!(RCC_CR & RCC_CR_HSERDY)) {
    }
    /* PLL: M = 25 (1 MHz in), N = 192, P = 2 (96 MHz), Q = 4 (48 MHz), source HSE; reserved bits kept */
    RCC_PLLCFGR = (RCC_PLLCFGR & ~0x0F437FFFu) | 25u | (192u << 6) | (0u << 16) | (1u << 22) | (4u << 24);
    RCC_CR |= RCC_CR_PLLON;
    while (!(RCC_CR & RCC_CR_PLLRDY)) {
    }
    FLASH_ACR = 3u | (1u << 8) | (1u << 9) | (1u << 10);      /* 3 wait states, prefetch, I and D caches */
    RCC_CFGR = (RCC_CFGR & ~0xFCF3u) | (4u << 10) | 2u;       /* AHB /1, APB1 /2, APB2 /1, SYSCLK = PLL */
    while (((RCC_CFGR >> 2) & 3u) != 2u) {
    }
}

static void pin_mode(uint32_t port, uint32_t pin, uint32_t mode, uint32_t af) {
    GPIO_MODER(port) = (GPIO_MODER(port) & ~(3u << (2 * pin))) | (mode << (2 * pin));
    GPIO_OSPEEDR(port) |= 2u << (2 * pin);                    /* fast */
    if (pin < 8)
        GPIO_AFRL(port) = (GPIO_AFRL(port) & ~(0xFu << (4 * pin))) | (af << (4 * pin));
    else
        GPIO_AFRH(port) = (GPIO_AFRH(port) & ~(0xFu << (4 * (pin - 8)))) | (af << (4 * (pin - 8)));
}

void board_gpio_init(void) {
    RCC_AHB1ENR |= (1u << 0) | (1u << 1) | (1u << 2);         /* GPIOA, GPIOB, GPIOC */
    for (uint32_t i = 0; i < TR_N_TAXELS; i++) pin_mode(GPIOA, i, 3u, 0u); /* PA0..: analog */
    pin_mode(GPIOA, 9, 2u, 7u);                               /* USART1 TX */
    pin_mode(GPIOA, 10, 2u, 7u);                              /* USART1 RX */
    if (LINK_CTS) pin_mode(GPIOA, 11, 2u, 7u);                /* USART1 CTS */
    pin_mode(GPIOB, 6, 2u, 4u);                               /* I2C1 SCL */
    pin_mode(GPIOB, 7, 2u, 4u);                               /* I2C1 SDA */
    GPIO_OTYPER(GPIOB) |= (1u << 6) | (1u << 7);              /* open drain */
    GPIO_PUPDR(GPIOB) = (GPIO_PUPDR(GPIOB) & ~(0xFu << 12)) | (0x5u << 12); /* weak pull-ups (add 4.7 k) */
    pin_mode(GPIOC, 13, 1u, 0u);                              /* on-board LED, active low */
    GPIO_BSRR(GPIOC) = 1u << 13;                              /* off */
}

void board_timer_init(void) {
    RCC_APB1ENR |= 1u << 0;                                   /* TIM2 */
    TIM2_PSC = SYSCLK_HZ / 1000000u - 1u;                     /* APB1 timer clock = 2 x APB1 = 96 MHz -> 1 MHz */
    TIM2_ARR = 0xFFFFFFFFu;
    TIM2_EGR = 1u;                                            /* load the prescaler */
    TIM2_SR = 0;
    TIM2_CR1 = 1u;
}

uint32_t board_micros(void) { return TIM2_CNT; }

void board_tick_start(uint32_t at_us) {
    TIM2_CCR1 = at_us;
    TIM2_SR = ~TIM_CC1;
    TIM2_DIER = TIM_CC1;
}

uint32_t board_tick_next(uint32_t period_us) {
    uint32_t tick = TIM2_CCR1;
    TIM2_SR = ~TIM_CC1;                                       /* rc_w0: writing 1 elsewhere leaves other flags */
    TIM2_CCR1 = tick + period_us;                             /* exact grid, whatever the interrupt latency */
    return tick;
}

void board_delay_us(uint32_t us) {
    uint32_t start = TIM2_CNT;
    while (TIM2_CNT - start < us) {
    }
}

void board_led_toggle(void) { GPIO_ODR(GPIOC) ^= 1u << 13; }

void board_irq_enable(uint32_t irq, uint8_t priority) {
    NVIC_IPR(irq) = (uint8_t)(priority << 4);
    NVIC_ISER(irq / 32) = 1u << (irq % 32);
}

void board_irq_disable(uint32_t irq) {
    NVIC_ICER(irq / 32) = 1u << (irq % 32);
    __asm__ volatile("dsb\n isb" ::: "memory");
}

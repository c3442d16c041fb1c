/* Reset and vector table of the STM32F411 (RM0383 table 37): .data/.bss set-up, FPU on, then main. */
#include <stdint.h>

#include "regs.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
int main(void);
void Reset_Handler(void);
void TIM2_IRQHandler(void);
void USART1_IRQHandler(void);

/* Any interrupt nobody handles (faults included) stops here, where a debugger finds it. */
static void Default_Handler(void) {
    for (;;) {
    }
}

#define N_IRQ 86u
#define IRQ(n) (16u + (n))

/* GNU C range designators: every slot defaults, then the two handlers this firmware has. */
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Woverride-init"
__attribute__((section(".isr_vector"), used)) static void (*const vectors[16u + N_IRQ])(void) = {
    [0] = (void (*)(void))&_estack,
    [1] = Reset_Handler,
    [2 ... 15] = Default_Handler,
    [IRQ(0)... IRQ(N_IRQ - 1u)] = Default_Handler,
    [IRQ(IRQ_TIM2)] = TIM2_IRQHandler,
    [IRQ(IRQ_USART1)] = USART1_IRQHandler,
};
#pragma GCC diagnostic pop

void Reset_Handler(void) {
    uint32_t *src = &_sidata;
    for (uint32_t *dst = &_sdata; dst < &_edata;) *dst++ = *src++;
    for (uint32_t *dst = &_sbss; dst < &_ebss;) *dst++ = 0;
    SCB_CPACR |= 0xFu << 20;                                  /* CP10, CP11: the FPU, for float samples */
    __asm__ volatile("dsb\n isb");
    main();
    Default_Handler();
}

/* The serial link: USART1 at LINK_BAUD, 8N1, sending the core's ring from its TX-empty interrupt. */
#include "board.h"

#include "config.h"
#include "regs.h"

static tr_ring_t *tx;

void link_init(tr_ring_t *ring) {
    tx = ring;
    RCC_APB2ENR |= 1u << 4;                                   /* USART1 */
    USART1_BRR = (APB2_HZ + LINK_BAUD / 2u) / LINK_BAUD;      /* oversampling 16: 921600 -> 923077 baud (+0.16 %) */
    USART1_CR3 = LINK_CTS ? USART_CR3_CTSE : 0u;
    USART1_CR1 = USART_CR1_UE | USART_CR1_TE;
}

void link_kick(void) {
    if (tr_ring_used(tx) > 0) USART1_CR1 |= USART_CR1_TXEIE;
}

void USART1_IRQHandler(void) {
    const uint8_t *p;
    if (!(USART1_SR & USART_SR_TXE)) return;
    if (tr_ring_peek(tx, &p) > 0) {
        USART1_DR = *p;
        tr_ring_consume(tx, 1);
    } else {
        USART1_CR1 &= ~USART_CR1_TXEIE;                       /* empty: link_kick restarts it */
    }
}

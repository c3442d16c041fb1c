/* The few STM32F411 registers this firmware touches (RM0383), as plain volatile addresses. */
#ifndef TR_BOARD_REGS_H
#define TR_BOARD_REGS_H

#include <stdint.h>

#define REG(addr) (*(volatile uint32_t *)(addr))

/* RCC */
#define RCC_CR REG(0x40023800u)
#define RCC_PLLCFGR REG(0x40023804u)
#define RCC_CFGR REG(0x40023808u)
#define RCC_AHB1ENR REG(0x40023830u)
#define RCC_APB1ENR REG(0x40023840u)
#define RCC_APB2ENR REG(0x40023844u)
#define RCC_CR_HSEON (1u << 16)
#define RCC_CR_HSERDY (1u << 17)
#define RCC_CR_PLLON (1u << 24)
#define RCC_CR_PLLRDY (1u << 25)

/* FLASH, PWR */
#define FLASH_ACR REG(0x40023C00u)
#define PWR_CR REG(0x40007000u)

/* GPIO (x: port base) */
#define GPIOA 0x40020000u
#define GPIOB 0x40020400u
#define GPIOC 0x40020800u
#define GPIO_MODER(x) REG((x) + 0x00u)
#define GPIO_OTYPER(x) REG((x) + 0x04u)
#define GPIO_OSPEEDR(x) REG((x) + 0x08u)
#define GPIO_PUPDR(x) REG((x) + 0x0Cu)
#define GPIO_ODR(x) REG((x) + 0x14u)
#define GPIO_BSRR(x) REG((x) + 0x18u)
#define GPIO_AFRL(x) REG((x) + 0x20u)
#define GPIO_AFRH(x) REG((x) + 0x24u)

/* TIM2: 32-bit, the microsecond clock and the 2 kHz sampling compare */
#define TIM2_CR1 REG(0x40000000u)
#define TIM2_DIER REG(0x4000000Cu)
#define TIM2_SR REG(0x40000010u)
#define TIM2_EGR REG(0x40000014u)
#define TIM2_CNT REG(0x40000024u)
#define TIM2_PSC REG(0x40000028u)
#define TIM2_ARR REG(0x4000002Cu)
#define TIM2_CCR1 REG(0x40000034u)
#define TIM_CC1 (1u << 1)

/* ADC1 and the common block */
#define ADC1_SR REG(0x40012000u)
#define ADC1_CR1 REG(0x40012004u)
#define ADC1_CR2 REG(0x40012008u)
#define ADC1_SMPR1 REG(0x4001200Cu)
#define ADC1_SMPR2 REG(0x40012010u)
#define ADC1_SQR1 REG(0x4001202Cu)
#define ADC1_SQR3 REG(0x40012034u)
#define ADC1_DR REG(0x4001204Cu)
#define ADC_CCR REG(0x40012304u)
#define ADC_SR_EOC (1u << 1)
#define ADC_CR2_ADON (1u << 0)
#define ADC_CR2_SWSTART (1u << 30)
#define ADC_CCR_TSVREFE (1u << 23)
#define ADC_CH_TEMP 18u

/* I2C1 */
#define I2C1_CR1 REG(0x40005400u)
#define I2C1_CR2 REG(0x40005404u)
#define I2C1_DR REG(0x40005410u)
#define I2C1_SR1 REG(0x40005414u)
#define I2C1_SR2 REG(0x40005418u)
#define I2C1_CCR REG(0x4000541Cu)
#define I2C1_TRISE REG(0x40005420u)
#define I2C_CR1_PE (1u << 0)
#define I2C_CR1_START (1u << 8)
#define I2C_CR1_STOP (1u << 9)
#define I2C_CR1_ACK (1u << 10)
#define I2C_CR1_SWRST (1u << 15)
#define I2C_SR1_SB (1u << 0)
#define I2C_SR1_ADDR (1u << 1)
#define I2C_SR1_BTF (1u << 2)
#define I2C_SR1_RXNE (1u << 6)
#define I2C_SR1_TXE (1u << 7)
#define I2C_SR1_ERRORS (0xDF00u)           /* BERR ARLO AF OVR PECERR TIMEOUT SMBALERT */
#define I2C_SR2_BUSY (1u << 1)

/* USART1 */
#define USART1_SR REG(0x40011000u)
#define USART1_DR REG(0x40011004u)
#define USART1_BRR REG(0x40011008u)
#define USART1_CR1 REG(0x4001100Cu)
#define USART1_CR3 REG(0x40011014u)
#define USART_SR_TXE (1u << 7)
#define USART_CR1_TE (1u << 3)
#define USART_CR1_TXEIE (1u << 7)
#define USART_CR1_UE (1u << 13)
#define USART_CR3_CTSE (1u << 9)

/* Cortex-M4 core */
#define NVIC_ISER(n) REG(0xE000E100u + 4u * (n))
#define NVIC_ICER(n) REG(0xE000E180u + 4u * (n))
#define NVIC_IPR(irq) (*(volatile uint8_t *)(0xE000E400u + (irq)))
#define SCB_CPACR REG(0xE000ED88u)
#define IRQ_TIM2 28u
#define IRQ_USART1 37u

/* 96-bit unique device ID */
#define UID(n) REG(0x1FFF7A10u + 4u * (n))

#endif

/* PVDF films through their charge amplifiers into ADC1 (PA0..PA7), and ADC noise for the boot session. */
#include "board.h"

#include "config.h"
#include "regs.h"

static float bias_counts[TR_N_TAXELS];

void pvdf_init(void) {
    RCC_APB2ENR |= 1u << 8;                                   /* ADC1 */
    ADC_CCR = (1u << 16) | ADC_CCR_TSVREFE;                   /* ADCCLK = APB2 / 4 = 24 MHz; temperature sensor on */
    ADC1_CR1 = 0;                                             /* 12 bits, one channel per conversion */
    uint32_t smpr2 = 0;
    for (uint32_t ch = 0; ch < 8; ch++) smpr2 |= PVDF_ADC_SAMPLE_CYCLES << (3 * ch);
    ADC1_SMPR2 = smpr2;
    ADC1_SMPR1 = 7u << (3 * (ADC_CH_TEMP - 10));              /* 480 cycles: the temperature sensor needs >= 10 us */
    ADC1_SQR1 = 0;                                            /* sequence length 1 */
    ADC1_CR2 = ADC_CR2_ADON;
    board_delay_us(10);                                       /* ADC and sensor start-up */
    for (uint32_t i = 0; i < TR_N_TAXELS; i++) bias_counts[i] = PVDF_BIAS_COUNTS;
}

uint16_t adc_read(uint32_t channel) {
    ADC1_SQR3 = channel;
    ADC1_CR2 |= ADC_CR2_SWSTART;
    while (!(ADC1_SR & ADC_SR_EOC)) {
    }
    return (uint16_t)ADC1_DR;                                 /* reading DR clears EOC */
}

void pvdf_calibrate(void) {
    if (PVDF_BIAS_SAMPLES == 0) return;
    for (uint32_t i = 0; i < TR_N_TAXELS; i++) {
        uint32_t sum = 0;
        for (uint32_t k = 0; k < PVDF_BIAS_SAMPLES; k++) {
            sum += adc_read(i);
            board_delay_us(TR_PVDF_PERIOD_US / 8u);
        }
        bias_counts[i] = (float)sum / (float)PVDF_BIAS_SAMPLES;
    }
}

void pvdf_read(float *volts) {
    for (uint32_t i = 0; i < TR_N_TAXELS; i++) volts[i] = ((float)adc_read(i) - bias_counts[i]) * PVDF_VOLTS_PER_COUNT;
}

uint32_t adc_entropy(void *ctx) {
    uint32_t *round = ctx, bits = 0;
    for (int k = 0; k < 32; k++) bits = (bits << 1) | (adc_read(ADC_CH_TEMP) & 1u); /* thermal noise LSBs */
    (*round)++;
    return bits ^ UID(*round % 3u) ^ board_micros();
}

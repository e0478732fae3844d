/*
 * magcoil.ino — board file of the coil amplifier board (Arduino / Teensy), around firmware/magcoil/magcoil.c.
 *
 * Everything that matters for safety (protocol, ratings, sequence numbers, the deadline) is in magcoil.c and
 * tested on the host; this file only moves bytes between USB serial and magcoil_step(), passes micros() as
 * the clock, and drives the amplifiers. Build: docs/coil-board.md ("Building the board firmware").
 *
 * The loop never blocks: bytes are read only when available and replies are queued and written only as far as
 * the serial transmit buffer has room (a full queue drops replies: the host retries), so a host that stops
 * reading cannot stall the deadline check that runs on every pass.
 */
#include "magcoil.h"

static const unsigned long BAUD = 115200;  /* USB CDC boards (Teensy, Leonardo) ignore it */

static magcoil_t board;
static magcoil_outputs_t playing;          /* what the amplifiers are set to (copied by magcoil_output) */
static uint32_t phase;                     /* sine phase, 2^-32 cycles */
static uint32_t last_us;

/* ==== THE PLACE A LAB WIRES ITS AMPLIFIER'S DAC ======================================================
 * Placeholders: one PWM pin per channel for the current's magnitude, one pin for its sign, full scale
 * FULL_SCALE_UA. Replace amp_write() with your amplifier's interface (SPI DAC, I2C DAC, Teensy analog out,
 * an enable line...). Keep zero current = all pins low, so that a board in reset drives no current.
 */
static const uint8_t PWM_PIN[MAGCOIL_NCH] = {2, 3, 4, 5, 6, 9};   /* placeholder pins */
static const uint8_t DIR_PIN[MAGCOIL_NCH] = {10, 11, 12, 14, 15, 16};
static const uint32_t FULL_SCALE_UA = 3000000UL;                   /* amplifier full scale, uA */
static const uint32_t PWM_MAX = 255;                               /* analogWrite resolution (8 bit) */

static void amp_write(unsigned ch, int32_t ua)
{
    uint32_t mag = ua < 0 ? 0UL - (uint32_t)ua : (uint32_t)ua;
    if (mag > FULL_SCALE_UA) {
        mag = FULL_SCALE_UA;
    }
    digitalWrite(DIR_PIN[ch], ua < 0 ? HIGH : LOW);
    analogWrite(PWM_PIN[ch], (int)((mag / 1000UL) * PWM_MAX / (FULL_SCALE_UA / 1000UL)));
}
/* ==== end of the amplifier placeholders ============================================================== */

static void write_amplifiers(void)
{
    for (unsigned ch = 0; ch < MAGCOIL_NCH; ch++) {
        amp_write(ch, magcoil_current_ua(&playing, ch, phase));
    }
}

/* The output stage magcoil.c calls whenever the outputs change (a SET, a ZERO, a deadline trip, power-up):
 * applied at once, not at the next waveform update. */
extern "C" void magcoil_output(const magcoil_outputs_t *o, void *ctx)
{
    (void)ctx;
    playing = *o;
    write_amplifiers();
}

void setup()
{
    for (unsigned ch = 0; ch < MAGCOIL_NCH; ch++) {
        pinMode(PWM_PIN[ch], OUTPUT);
        pinMode(DIR_PIN[ch], OUTPUT);
    }
    magcoil_init(&board, NULL);  /* outputs zero */
    Serial.begin(BAUD);
    last_us = (uint32_t)micros();
}

void loop()
{
    /* Replies wait in txq and leave as fast as the serial port takes them: never a blocking write (a 64-byte
     * UART buffer cannot take a 96-byte STATUS at once; a USB host that stops reading must not stall us). */
    static uint8_t txq[4 * MAGCOIL_MAX_REPLY];
    static size_t txq_len = 0;
    uint8_t rx[32];
    size_t n = 0;
    while (n < sizeof rx && Serial.available() > 0) {
        rx[n++] = (uint8_t)Serial.read();
    }
    uint32_t now = (uint32_t)micros();
    /* also the deadline check, on every pass; replies that do not fit in txq are dropped (tx_dropped) */
    txq_len += magcoil_step(&board, now, rx, n, txq + txq_len, sizeof txq - txq_len);
    int room = Serial.availableForWrite();
    if (txq_len > 0 && room > 0) {
        size_t w = Serial.write(txq, txq_len < (size_t)room ? txq_len : (size_t)room);
        memmove(txq, txq + w, txq_len - w);
        txq_len -= w;
    }
    phase += magcoil_phase_step(playing.freq_mhz, now - last_us);
    last_us = now;
    write_amplifiers();
}

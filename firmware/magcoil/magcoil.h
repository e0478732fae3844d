/*
 * magcoil — the coil amplifier board's protocol, deadline and output stage, portable C99.
 *
 * One entry function, magcoil_step(), consumes the bytes received since the last call at the
 * board's time now_us, applies the valid frames, enforces the deadline and writes the replies.
 * The board file provides magcoil_output(), the output stage (DAC, PWM, a lab's amplifier),
 * called whenever the outputs change. Integers only: no floats, no malloc, no OS calls; the
 * only headers are <stdint.h> and <stddef.h>. The protocol is described in docs/coil-board.md.
 *
 * Units: currents in signed microamps (int32_t, resolution 1 uA, range +-2147 A), frequency in
 * millihertz (uint32_t), time in microseconds (uint32_t, wrapping every 71.6 minutes; all time
 * arithmetic is modular, so magcoil_step() must be called at least every 2^31 us — in practice,
 * every pass of the board's main loop).
 *
 * Safety rules (each enforced in magcoil.c, each tested in tests/rig/devices/):
 *   - power-up: outputs zero (magcoil_init calls magcoil_output with zeros);
 *   - deadline: when no SET was accepted for deadline_us, the outputs go to zero and the TRIPPED
 *     flag is set; only an accepted SET restarts the deadline (PING, CONFIG, INFO, ZERO do not);
 *   - ratings: a SET whose |dc|+|ac| exceeds a channel's rating, or whose frequency exceeds
 *     MAGCOIL_FREQ_MAX_MHZ, is refused (NAK) and the outputs are unchanged;
 *   - CONFIG cannot set a deadline of 0 or above MAGCOIL_DEADLINE_MAX_US;
 *   - a SET's sequence number must be newer than the last accepted SET or CONFIG (serial-number
 *     arithmetic modulo 2^16), else it is refused as stale;
 *   - a frame with a bad CRC or an impossible length is dropped and the parser resynchronises
 *     on the next sync bytes (bytes after the false sync are rescanned, none is skipped);
 *   - a ZERO frame zeroes the outputs at once, whatever its sequence number.
 */
#ifndef MAGCOIL_H
#define MAGCOIL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" { /* the Arduino board file is C++ */
#endif

/* --- compile-time configuration (override with -D) ------------------------------------------ */
#define MAGCOIL_NCH 6

/* Per-channel peak current ratings, uA: a SET with |dc|+|ac| above them is refused.
 * Default: the coils of models/coils.toml (3 A in-plane, 2 A vertical). */
#ifndef MAGCOIL_RATINGS_UA
#define MAGCOIL_RATINGS_UA {3000000L, 3000000L, 3000000L, 3000000L, 2000000L, 2000000L}
#endif
/* Highest sine frequency accepted, mHz (1000 Hz). */
#ifndef MAGCOIL_FREQ_MAX_MHZ
#define MAGCOIL_FREQ_MAX_MHZ 1000000UL
#endif
/* The longest deadline a CONFIG frame may set, us (500 ms). */
#ifndef MAGCOIL_DEADLINE_MAX_US
#define MAGCOIL_DEADLINE_MAX_US 500000UL
#endif
/* The deadline at power-up, us (100 ms; must not exceed MAGCOIL_DEADLINE_MAX_US). */
#ifndef MAGCOIL_DEADLINE_DEFAULT_US
#define MAGCOIL_DEADLINE_DEFAULT_US 100000UL
#endif
/* A partial frame older than this (no byte received for this long) is dropped and rescanned, us. */
#ifndef MAGCOIL_RX_GAP_US
#define MAGCOIL_RX_GAP_US 20000UL
#endif

/* --- protocol constants (docs/coil-board.md) -------------------------------------------------- */
#define MAGCOIL_SYNC0 0xA5u
#define MAGCOIL_SYNC1 0x5Au
#define MAGCOIL_VERSION 1u
#define MAGCOIL_HEADER 6u        /* sync0 sync1 type seq_lo seq_hi len */
#define MAGCOIL_MAX_PAYLOAD 96u
#define MAGCOIL_MAX_FRAME (MAGCOIL_HEADER + MAGCOIL_MAX_PAYLOAD + 2u)

/* frame types, host -> board */
#define MAGCOIL_PING 0x01u
#define MAGCOIL_SET 0x02u
#define MAGCOIL_ZERO 0x03u
#define MAGCOIL_CONFIG 0x04u
#define MAGCOIL_INFO 0x05u
/* frame types, board -> host */
#define MAGCOIL_STATUS 0x81u
#define MAGCOIL_NAK 0x82u
#define MAGCOIL_INFO_REPLY 0x85u

/* payload lengths */
#define MAGCOIL_SET_LEN (8u * MAGCOIL_NCH + 4u)     /* 52 */
#define MAGCOIL_CONFIG_LEN 4u
#define MAGCOIL_STATUS_LEN 88u
#define MAGCOIL_NAK_LEN 3u
#define MAGCOIL_INFO_LEN 44u
#define MAGCOIL_MAX_REPLY (MAGCOIL_HEADER + MAGCOIL_STATUS_LEN + 2u)   /* 96 bytes */

/* NAK reason codes */
#define MAGCOIL_R_BAD_LENGTH 1u     /* payload length wrong for the frame type */
#define MAGCOIL_R_UNKNOWN_TYPE 2u   /* not a host -> board frame type */
#define MAGCOIL_R_STALE_SEQ 3u      /* SET sequence number not newer than the last accepted */
#define MAGCOIL_R_OVER_RATING 4u    /* SET |dc|+|ac| above a channel's rating (detail: channel) */
#define MAGCOIL_R_FREQ_RANGE 5u     /* SET frequency above MAGCOIL_FREQ_MAX_MHZ */
#define MAGCOIL_R_DEADLINE_RANGE 6u /* CONFIG deadline 0 or above MAGCOIL_DEADLINE_MAX_US */

/* STATUS flags */
#define MAGCOIL_F_TRIPPED 0x01u  /* the deadline zeroed the outputs since the last accepted SET */
#define MAGCOIL_F_ARMED 0x02u    /* outputs on, the deadline running */

/* The outputs: i_k(t) = dc_ua[k] + ac_ua[k] * sin(2 pi freq t). */
typedef struct {
    int32_t dc_ua[MAGCOIL_NCH];
    int32_t ac_ua[MAGCOIL_NCH];
    uint32_t freq_mhz;
} magcoil_outputs_t;

typedef struct {
    uint32_t frames_ok;      /* frames applied (valid CRC, not refused) */
    uint32_t crc_errors;     /* frames dropped for a bad CRC */
    uint32_t malformed;      /* impossible lengths and partial frames dropped after a gap */
    uint32_t rejected;       /* frames refused with a NAK */
    uint32_t deadline_trips; /* times the deadline zeroed the outputs */
    uint32_t tx_dropped;     /* replies that did not fit in the caller's tx buffer */
} magcoil_counters_t;

/* The board's whole state; initialise with magcoil_init(), then only pass it to magcoil_step(). */
typedef struct {
    magcoil_outputs_t out;
    magcoil_counters_t cnt;
    void *ctx;
    uint32_t deadline_us;
    uint32_t last_set_us;
    uint32_t last_rx_us;
    uint32_t now_us;
    uint16_t last_seq;
    uint8_t have_seq;
    uint8_t armed;
    uint8_t tripped;
    uint8_t rx_len;
    uint8_t rx[MAGCOIL_MAX_FRAME];
} magcoil_t;

/* The output stage, provided by the board file: set the amplifiers to *o. Called by
 * magcoil_init() (zeros) and by magcoil_step() whenever the outputs change. */
void magcoil_output(const magcoil_outputs_t *o, void *ctx);

/* Power-up: outputs zero (magcoil_output is called once), default deadline, counters zero. */
void magcoil_init(magcoil_t *b, void *ctx);

/* Consume n_rx received bytes at time now_us: check the deadline, parse, apply valid frames,
 * and write at most tx_cap reply bytes into tx. Returns the number of reply bytes written.
 * Replies that do not fit are dropped (counted in tx_dropped; the host retries on timeout);
 * tx_cap >= 2 * MAGCOIL_MAX_REPLY is enough when bytes are passed a few at a time.
 * Call it with n_rx = 0 on every pass of the main loop so that the deadline is enforced. */
size_t magcoil_step(magcoil_t *b, uint32_t now_us, const uint8_t *rx, size_t n_rx, uint8_t *tx, size_t tx_cap);

/* The channel ratings compiled in, uA. */
extern const int32_t magcoil_ratings_ua[MAGCOIL_NCH];

/* CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor) of data[0..n). */
uint16_t magcoil_crc16(const uint8_t *data, size_t n);

/* Waveform helpers for a board that generates the sine itself (integers only):
 * magcoil_phase_step() is the phase advance, in 2^-32 cycles, of freq_mhz over dt_us (exact to one
 * phase unit for any arguments); magcoil_sin_q15() is sin(2 pi phase / 2^32) in
 * Q15 (+-32767); magcoil_current_ua() is channel ch's current dc + ac * sin at that phase. */
uint32_t magcoil_phase_step(uint32_t freq_mhz, uint32_t dt_us);
int32_t magcoil_sin_q15(uint32_t phase);
int32_t magcoil_current_ua(const magcoil_outputs_t *o, unsigned ch, uint32_t phase);

#ifdef __cplusplus
}
#endif

#endif /* MAGCOIL_H */

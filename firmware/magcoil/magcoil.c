/*
 * magcoil — protocol parser, deadline and output stage of the coil amplifier board (magcoil.h).
 * Portable C99, integers only; the frame layout is in docs/coil-board.md.
 */
#include "magcoil.h"

const int32_t magcoil_ratings_ua[MAGCOIL_NCH] = MAGCOIL_RATINGS_UA;

/* Reply bytes go here; a reply that does not fit is dropped whole (never truncated). */
typedef struct {
    uint8_t *p;
    size_t cap;
    size_t n;
} txbuf_t;

/* --- little-endian fields --------------------------------------------------------------------- */
/* Shifts on unsigned operands: with a 16-bit int (AVR) a uint8_t promotes to int and 0xFF << 8 overflows it. */
static uint16_t rd_u16(const uint8_t *p) { return (uint16_t)((unsigned)p[0] | ((unsigned)p[1] << 8)); }

static uint32_t rd_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* Two's complement decode without relying on implementation-defined unsigned -> signed casts. */
static int32_t rd_i32(const uint8_t *p)
{
    uint32_t u = rd_u32(p);
    if (u <= 0x7FFFFFFFul) {
        return (int32_t)u;
    }
    return -(int32_t)(~u) - 1;
}

static void wr_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void wr_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

static void wr_i32(uint8_t *p, int32_t v) { wr_u32(p, (uint32_t)v); }

/* |v| as an unsigned number (also right for INT32_MIN). */
static uint32_t magnitude(int32_t v) { return v < 0 ? 0u - (uint32_t)v : (uint32_t)v; }

/* --- CRC ---------------------------------------------------------------------------------------- */
uint16_t magcoil_crc16(const uint8_t *data, size_t n)
{
    uint16_t crc = 0xFFFFu;
    size_t i;
    unsigned bit;
    for (i = 0; i < n; i++) {
        crc = (uint16_t)(crc ^ (uint16_t)((unsigned)data[i] << 8));
        for (bit = 0; bit < 8u; bit++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

/* --- outputs ------------------------------------------------------------------------------------ */
static int outputs_equal(const magcoil_outputs_t *a, const magcoil_outputs_t *b)
{
    unsigned k;
    if (a->freq_mhz != b->freq_mhz) {
        return 0;
    }
    for (k = 0; k < MAGCOIL_NCH; k++) {
        if (a->dc_ua[k] != b->dc_ua[k] || a->ac_ua[k] != b->ac_ua[k]) {
            return 0;
        }
    }
    return 1;
}

static int outputs_zero(const magcoil_outputs_t *o)
{
    unsigned k;
    for (k = 0; k < MAGCOIL_NCH; k++) {
        if (o->dc_ua[k] != 0 || o->ac_ua[k] != 0) {
            return 0;
        }
    }
    return 1;
}

/* The only place the outputs change: the output stage is called when (and only when) they do. */
static void set_outputs(magcoil_t *b, const magcoil_outputs_t *o)
{
    if (!outputs_equal(&b->out, o)) {
        b->out = *o;
        magcoil_output(&b->out, b->ctx);
    }
}

static void zero_outputs(magcoil_t *b)
{
    magcoil_outputs_t z;
    unsigned k;
    for (k = 0; k < MAGCOIL_NCH; k++) {
        z.dc_ua[k] = 0;
        z.ac_ua[k] = 0;
    }
    z.freq_mhz = 0;
    b->armed = 0;
    set_outputs(b, &z);
}

/* The deadline rule: outputs armed by a SET at last_set_us go to zero once deadline_us have passed. */
static void check_deadline(magcoil_t *b)
{
    if (b->armed && (uint32_t)(b->now_us - b->last_set_us) >= b->deadline_us) {
        zero_outputs(b);
        b->tripped = 1;
        b->cnt.deadline_trips++;
    }
}

void magcoil_init(magcoil_t *b, void *ctx)
{
    unsigned k;
    for (k = 0; k < MAGCOIL_NCH; k++) {
        b->out.dc_ua[k] = 0;
        b->out.ac_ua[k] = 0;
    }
    b->out.freq_mhz = 0;
    b->cnt.frames_ok = 0;
    b->cnt.crc_errors = 0;
    b->cnt.malformed = 0;
    b->cnt.rejected = 0;
    b->cnt.deadline_trips = 0;
    b->cnt.tx_dropped = 0;
    b->ctx = ctx;
    b->deadline_us = (uint32_t)MAGCOIL_DEADLINE_DEFAULT_US;
    b->last_set_us = 0;
    b->last_rx_us = 0;
    b->now_us = 0;
    b->last_seq = 0;
    b->have_seq = 0;
    b->armed = 0;
    b->tripped = 0;
    b->rx_len = 0;
    magcoil_output(&b->out, b->ctx);
}

/* --- replies ------------------------------------------------------------------------------------ */
static void reply(magcoil_t *b, txbuf_t *t, uint8_t type, uint16_t seq, const uint8_t *payload, uint8_t len)
{
    size_t total = (size_t)MAGCOIL_HEADER + len + 2u;
    uint8_t *f;
    uint16_t crc;
    unsigned i;
    if (t->p == NULL || t->cap - t->n < total) {
        b->cnt.tx_dropped++;
        return;
    }
    f = t->p + t->n;
    f[0] = MAGCOIL_SYNC0;
    f[1] = MAGCOIL_SYNC1;
    f[2] = type;
    wr_u16(f + 3, seq);
    f[5] = len;
    for (i = 0; i < len; i++) {
        f[MAGCOIL_HEADER + i] = payload[i];
    }
    crc = magcoil_crc16(f + 2, (size_t)4u + len);
    wr_u16(f + MAGCOIL_HEADER + len, crc);
    t->n += total;
}

static void reply_status(magcoil_t *b, txbuf_t *t, uint16_t seq)
{
    uint8_t p[MAGCOIL_STATUS_LEN];
    unsigned k;
    p[0] = (uint8_t)((b->tripped ? MAGCOIL_F_TRIPPED : 0u) | (b->armed ? MAGCOIL_F_ARMED : 0u));
    p[1] = MAGCOIL_NCH;
    wr_u16(p + 2, b->last_seq);
    wr_u32(p + 4, b->deadline_us);
    wr_u32(p + 8, b->armed ? (uint32_t)(b->now_us - b->last_set_us) : 0xFFFFFFFFul);
    for (k = 0; k < MAGCOIL_NCH; k++) {
        wr_i32(p + 12 + 4 * k, b->out.dc_ua[k]);
        wr_i32(p + 36 + 4 * k, b->out.ac_ua[k]);
    }
    wr_u32(p + 60, b->out.freq_mhz);
    wr_u32(p + 64, b->cnt.frames_ok);
    wr_u32(p + 68, b->cnt.crc_errors);
    wr_u32(p + 72, b->cnt.malformed);
    wr_u32(p + 76, b->cnt.rejected);
    wr_u32(p + 80, b->cnt.deadline_trips);
    wr_u32(p + 84, b->cnt.tx_dropped);
    reply(b, t, MAGCOIL_STATUS, seq, p, (uint8_t)MAGCOIL_STATUS_LEN);
}

static void reply_info(magcoil_t *b, txbuf_t *t, uint16_t seq)
{
    uint8_t p[MAGCOIL_INFO_LEN];
    unsigned k;
    p[0] = MAGCOIL_VERSION;
    p[1] = MAGCOIL_NCH;
    wr_u16(p + 2, 0);
    for (k = 0; k < MAGCOIL_NCH; k++) {
        wr_i32(p + 4 + 4 * k, magcoil_ratings_ua[k]);
    }
    wr_u32(p + 28, (uint32_t)MAGCOIL_FREQ_MAX_MHZ);
    wr_u32(p + 32, (uint32_t)MAGCOIL_DEADLINE_MAX_US);
    wr_u32(p + 36, b->deadline_us);
    wr_u32(p + 40, (uint32_t)MAGCOIL_RX_GAP_US);
    reply(b, t, MAGCOIL_INFO_REPLY, seq, p, (uint8_t)MAGCOIL_INFO_LEN);
}

static void nak(magcoil_t *b, txbuf_t *t, uint8_t type, uint16_t seq, uint8_t reason, uint8_t detail)
{
    uint8_t p[MAGCOIL_NAK_LEN];
    p[0] = reason;
    p[1] = detail;
    p[2] = type;
    b->cnt.rejected++;
    reply(b, t, MAGCOIL_NAK, seq, p, (uint8_t)MAGCOIL_NAK_LEN);
}

/* --- frames ------------------------------------------------------------------------------------- */
/* Serial-number arithmetic (RFC 1982) on 16 bits: seq is newer than last when 0 < seq - last < 2^15. */
static int seq_newer(uint16_t seq, uint16_t last)
{
    uint16_t d = (uint16_t)(seq - last);
    return d != 0u && d < 0x8000u;
}

/* SET: refused (NAK, outputs unchanged) when stale, above the frequency limit or over a rating;
 * else applied, and the only frame that restarts the deadline and clears TRIPPED. */
static void handle_set(magcoil_t *b, txbuf_t *t, uint16_t seq, const uint8_t *p, uint8_t len)
{
    magcoil_outputs_t o;
    unsigned k;
    if (len != MAGCOIL_SET_LEN) {
        nak(b, t, MAGCOIL_SET, seq, MAGCOIL_R_BAD_LENGTH, len);
        return;
    }
    if (b->have_seq && !seq_newer(seq, b->last_seq)) {
        nak(b, t, MAGCOIL_SET, seq, MAGCOIL_R_STALE_SEQ, 0);
        return;
    }
    for (k = 0; k < MAGCOIL_NCH; k++) {
        o.dc_ua[k] = rd_i32(p + 4 * k);
        o.ac_ua[k] = rd_i32(p + 4 * MAGCOIL_NCH + 4 * k);
    }
    o.freq_mhz = rd_u32(p + 8 * MAGCOIL_NCH);
    if (o.freq_mhz > (uint32_t)MAGCOIL_FREQ_MAX_MHZ) {
        nak(b, t, MAGCOIL_SET, seq, MAGCOIL_R_FREQ_RANGE, 0);
        return;
    }
    for (k = 0; k < MAGCOIL_NCH; k++) {
        uint32_t rating = magnitude(magcoil_ratings_ua[k]);
        uint32_t m_dc = magnitude(o.dc_ua[k]);
        uint32_t m_ac = magnitude(o.ac_ua[k]);
        if (m_dc > rating || m_ac > rating - m_dc) { /* |dc| + |ac| > rating, without overflow */
            nak(b, t, MAGCOIL_SET, seq, MAGCOIL_R_OVER_RATING, (uint8_t)k);
            return;
        }
    }
    b->last_seq = seq;
    b->have_seq = 1;
    b->last_set_us = b->now_us;
    b->tripped = 0;
    if (outputs_zero(&o)) { /* zero currents: nothing to time out */
        zero_outputs(b);
    } else {
        set_outputs(b, &o);
        b->armed = 1;
    }
    b->cnt.frames_ok++;
    reply_status(b, t, seq);
}

/* CONFIG: a deadline in (0, MAGCOIL_DEADLINE_MAX_US]; it starts a new sequence window (the next SET must
 * be newer than the CONFIG's seq), so a host that reconnects need not know the last seq used. */
static void handle_config(magcoil_t *b, txbuf_t *t, uint16_t seq, const uint8_t *p, uint8_t len)
{
    uint32_t d;
    if (len != MAGCOIL_CONFIG_LEN) {
        nak(b, t, MAGCOIL_CONFIG, seq, MAGCOIL_R_BAD_LENGTH, len);
        return;
    }
    d = rd_u32(p);
    if (d == 0u || d > (uint32_t)MAGCOIL_DEADLINE_MAX_US) {
        nak(b, t, MAGCOIL_CONFIG, seq, MAGCOIL_R_DEADLINE_RANGE, 0);
        return;
    }
    b->deadline_us = d;
    b->last_seq = seq;
    b->have_seq = 1;
    b->cnt.frames_ok++;
    check_deadline(b); /* a shorter deadline may already have passed */
    reply_status(b, t, seq);
}

static void handle_frame(magcoil_t *b, txbuf_t *t, uint8_t type, uint16_t seq, const uint8_t *p, uint8_t len)
{
    switch (type) {
    case MAGCOIL_SET:
        handle_set(b, t, seq, p, len);
        break;
    case MAGCOIL_CONFIG:
        handle_config(b, t, seq, p, len);
        break;
    case MAGCOIL_PING: /* a heartbeat is answered but does not restart the deadline */
    case MAGCOIL_ZERO:
    case MAGCOIL_INFO:
        if (len != 0u) {
            nak(b, t, type, seq, MAGCOIL_R_BAD_LENGTH, len);
            break;
        }
        if (type == MAGCOIL_ZERO) {
            zero_outputs(b); /* whatever the seq: zeroing is always safe */
        }
        b->cnt.frames_ok++;
        if (type == MAGCOIL_INFO) {
            reply_info(b, t, seq);
        } else {
            reply_status(b, t, seq);
        }
        break;
    default:
        nak(b, t, type, seq, MAGCOIL_R_UNKNOWN_TYPE, 0);
        break;
    }
}

/* --- parser ------------------------------------------------------------------------------------- */
static void rx_drop(magcoil_t *b, unsigned n)
{
    unsigned i;
    if (n >= b->rx_len) {
        b->rx_len = 0;
        return;
    }
    for (i = n; i < b->rx_len; i++) {
        b->rx[i - n] = b->rx[i];
    }
    b->rx_len = (uint8_t)(b->rx_len - n);
}

/* Resolve what the buffer holds: skip to a sync, drop false syncs (impossible length, bad CRC) by one byte so
 * that the bytes after them are rescanned, handle complete frames; stop when a frame is incomplete. */
static void rx_parse(magcoil_t *b, txbuf_t *t)
{
    for (;;) {
        unsigned i, len, total;
        if (b->rx_len == 0u) {
            return;
        }
        if (b->rx[0] != MAGCOIL_SYNC0) {
            for (i = 1; i < b->rx_len && b->rx[i] != MAGCOIL_SYNC0; i++) {
            }
            rx_drop(b, i);
            continue;
        }
        if (b->rx_len < 2u) {
            return;
        }
        if (b->rx[1] != MAGCOIL_SYNC1) {
            rx_drop(b, 1);
            continue;
        }
        if (b->rx_len < MAGCOIL_HEADER) {
            return;
        }
        len = b->rx[5];
        if (len > MAGCOIL_MAX_PAYLOAD) {
            b->cnt.malformed++;
            rx_drop(b, 1);
            continue;
        }
        total = MAGCOIL_HEADER + len + 2u;
        if (b->rx_len < total) {
            return;
        }
        if (magcoil_crc16(b->rx + 2, 4u + len) != rd_u16(b->rx + MAGCOIL_HEADER + len)) {
            b->cnt.crc_errors++;
            rx_drop(b, 1);
            continue;
        }
        handle_frame(b, t, b->rx[2], rd_u16(b->rx + 3), b->rx + MAGCOIL_HEADER, (uint8_t)len);
        rx_drop(b, total);
    }
}

size_t magcoil_step(magcoil_t *b, uint32_t now_us, const uint8_t *rx, size_t n_rx, uint8_t *tx, size_t tx_cap)
{
    txbuf_t t;
    size_t i;
    t.p = tx;
    t.cap = tx == NULL ? 0u : tx_cap;
    t.n = 0;
    b->now_us = now_us;
    check_deadline(b);
    /* A frame is sent in one burst; a partial frame after a silence is noise (or a false sync). */
    if (b->rx_len > 0u && (uint32_t)(now_us - b->last_rx_us) > (uint32_t)MAGCOIL_RX_GAP_US) {
        b->cnt.malformed++;
        while (b->rx_len > 0u) {
            rx_drop(b, 1);
            rx_parse(b, &t);
        }
    }
    for (i = 0; i < n_rx; i++) {
        if (b->rx_len >= MAGCOIL_MAX_FRAME) { /* cannot happen: a full buffer always resolves */
            rx_drop(b, 1);
        }
        b->rx[b->rx_len] = rx[i];
        b->rx_len++;
        b->last_rx_us = now_us;
        rx_parse(b, &t);
    }
    check_deadline(b);
    return t.n;
}

/* --- waveform helpers ----------------------------------------------------------------------------- */
/* sin(i * pi / 128) in Q15 for i = 0..64: a quarter wave, linearly interpolated. */
static const int16_t quarter_sine[65] = {
    0, 804, 1608, 2410, 3212, 4011, 4808, 5602,
    6393, 7179, 7962, 8739, 9512, 10278, 11039, 11793,
    12539, 13279, 14010, 14732, 15446, 16151, 16846, 17530,
    18204, 18868, 19519, 20159, 20787, 21403, 22005, 22594,
    23170, 23731, 24279, 24811, 25329, 25832, 26319, 26790,
    27245, 27683, 28105, 28510, 28898, 29268, 29621, 29956,
    30273, 30571, 30852, 31113, 31356, 31580, 31785, 31971,
    32137, 32285, 32412, 32521, 32609, 32678, 32728, 32757,
    32767,
};

uint32_t magcoil_phase_step(uint32_t freq_mhz, uint32_t dt_us)
{
    /* phase = frac(f[mHz] * dt[us] / 1e9 cycles) * 2^32; 2^32 / 1e9 = 2^23 / 1953125, and only the
     * remainder modulo 1e9 matters, so every product fits in 64 bits. */
    uint64_t r = ((uint64_t)freq_mhz * dt_us) % 1000000000u;
    return (uint32_t)((r << 23) / 1953125u);
}

int32_t magcoil_sin_q15(uint32_t phase)
{
    unsigned idx = (unsigned)(phase >> 24);
    unsigned quadrant = idx >> 6;
    unsigned i = idx & 63u;
    uint32_t frac = (phase >> 8) & 0xFFFFu;
    uint32_t a, c, m;
    if (quadrant & 1u) { /* falling quarter: mirror the table */
        a = (uint32_t)quarter_sine[64u - i];
        c = (uint32_t)quarter_sine[63u - i];
    } else {
        a = (uint32_t)quarter_sine[i];
        c = (uint32_t)quarter_sine[i + 1u];
    }
    m = c >= a ? (a << 16) + (c - a) * frac : (a << 16) - (a - c) * frac;
    m = (m + 0x8000u) >> 16;
    return quadrant >= 2u ? -(int32_t)m : (int32_t)m;
}

int32_t magcoil_current_ua(const magcoil_outputs_t *o, unsigned ch, uint32_t phase)
{
    int64_t v;
    if (ch >= MAGCOIL_NCH) {
        return 0;
    }
    v = (int64_t)o->dc_ua[ch] + ((int64_t)o->ac_ua[ch] * magcoil_sin_q15(phase)) / 32767;
    if (v > INT32_MAX) {
        return INT32_MAX;
    }
    if (v < INT32_MIN) {
        return INT32_MIN;
    }
    return (int32_t)v;
}

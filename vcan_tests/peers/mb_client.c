/* mb_client - an independent Modbus client for chcos' simulation tests, on libmodbus.
 *
 * Usage: mb_client tcp HOST PORT UNIT HEXPDU [noreply]
 *        mb_client rtu DEVICE UNIT HEXPDU [noreply]
 * Sends one raw request (UNIT and the PDU given in hex, function code first) with libmodbus'
 * own framing (MBAP header or RTU CRC) and prints one line to stdout:
 *     ADU <hex>          the whole answer as received (MBAP header or unit and CRC included)
 *     TIMEOUT            no answer within 0.5 s
 *     ERROR <text>       any other failure
 *     SENT               with "noreply" (a broadcast): the request went out, nothing awaited
 * RTU runs at 19200 8N1. Exits 0 after printing, 2 for bad arguments.
 */
#include <errno.h>
#include <modbus.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int parse_hex(const char *hex, uint8_t *out, int max) {
    int n = 0;
    size_t len = strlen(hex);
    if (len % 2 != 0)
        return -1;
    for (size_t i = 0; i < len && n < max; i += 2) {
        unsigned int byte;
        if (sscanf(hex + i, "%2x", &byte) != 1)
            return -1;
        out[n++] = (uint8_t)byte;
    }
    return n;
}

int main(int argc, char **argv) {
    if (argc < 5) {
        fprintf(stderr, "usage: %s tcp HOST PORT UNIT HEXPDU [noreply] | rtu DEVICE UNIT HEXPDU "
                        "[noreply]\n", argv[0]);
        return 2;
    }
    int tcp = strcmp(argv[1], "tcp") == 0;
    int at = tcp ? 4 : 3;
    if (argc < at + 2) {
        fprintf(stderr, "%s: missing UNIT or HEXPDU\n", argv[0]);
        return 2;
    }
    modbus_t *ctx = tcp ? modbus_new_tcp(argv[2], atoi(argv[3]))
                        : modbus_new_rtu(argv[2], 19200, 'N', 8, 1);
    if (ctx == NULL) {
        printf("ERROR %s\n", modbus_strerror(errno));
        return 0;
    }
    uint8_t req[MODBUS_MAX_ADU_LENGTH];
    req[0] = (uint8_t)atoi(argv[at]);
    int n = parse_hex(argv[at + 1], req + 1, (int)sizeof(req) - 1);
    if (n < 1) {
        fprintf(stderr, "%s: bad HEXPDU %s\n", argv[0], argv[at + 1]);
        return 2;
    }
    int noreply = argc > at + 2 && strcmp(argv[at + 2], "noreply") == 0;
    modbus_set_slave(ctx, req[0]);     /* libmodbus' RTU receive filters on it */
    modbus_set_response_timeout(ctx, 0, 500000);
    if (modbus_connect(ctx) == -1) {
        printf("ERROR %s\n", modbus_strerror(errno));
        modbus_free(ctx);
        return 0;
    }
    if (modbus_send_raw_request(ctx, req, n + 1) == -1) {
        printf("ERROR %s\n", modbus_strerror(errno));
    } else if (noreply) {
        printf("SENT\n");
    } else {
        uint8_t rsp[MODBUS_MAX_ADU_LENGTH];
        int rc = modbus_receive_confirmation(ctx, rsp);
        if (rc == -1 && errno == ETIMEDOUT) {
            printf("TIMEOUT\n");
        } else if (rc == -1) {
            printf("ERROR %s\n", modbus_strerror(errno));
        } else {
            printf("ADU ");
            for (int i = 0; i < rc; i++)
                printf("%02x", rsp[i]);
            printf("\n");
        }
    }
    fflush(stdout);
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}

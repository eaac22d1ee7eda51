/* rtu_slave - an independent Modbus RTU slave for chcos' peer tests, on libmodbus.
 *
 * Usage: rtu_slave DEVICE UNIT [RESPONSE_TIMEOUT_MS|default [REPLY_DELAY_MS]]
 * Opens DEVICE (a serial port or pty) at 19200 8N1 as unit UNIT with 16 coils, 16 discrete
 * inputs, 16 holding and 16 input registers (input register i holds 100 + i, holding register
 * i holds 1000 + i at start). Requests for other units are ignored, as on a real line.
 * After every request it answered it prints one line to stdout and flushes it:
 *     REQ <function> HR <h0> ... <h15> CO <c0..c15 as 0/1 digits>
 * so a test sees what the slave saw (the values written into its registers). "READY" is
 * printed once the port is open. Ends on EOF of the port or on SIGTERM.
 *
 * After a request for another unit, libmodbus takes the next frame on the line for that unit's
 * answer and ignores it; its response timeout is set to 50 ms so that an absent unit's request
 * (which nobody answers) costs the line 50 ms rather than the next request (the master's
 * request timeout must be longer, as it is on any multi-drop line). RESPONSE_TIMEOUT_MS sets
 * another one; "default" keeps libmodbus' own (500 ms), as a stock slave has it. REPLY_DELAY_MS
 * makes it answer that late (a slow slave: an answer that arrives after the master's timeout).
 */
#include <errno.h>
#include <modbus.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

int main(int argc, char **argv) {
    if (argc < 3 || argc > 5) {
        fprintf(stderr, "usage: %s DEVICE UNIT [RESPONSE_TIMEOUT_MS|default [REPLY_DELAY_MS]]\n",
                argv[0]);
        return 2;
    }
    long delay_ms = argc == 5 ? atol(argv[4]) : 0;
    int unit = atoi(argv[2]);
    modbus_t *ctx = modbus_new_rtu(argv[1], 19200, 'N', 8, 1);
    if (ctx == NULL || modbus_set_slave(ctx, unit) == -1) {
        fprintf(stderr, "rtu_slave: bad arguments: %s\n", modbus_strerror(errno));
        return 2;
    }
    if (argc == 3)
        modbus_set_response_timeout(ctx, 0, 50000);
    else if (strcmp(argv[3], "default") != 0) {
        long ms = atol(argv[3]);
        modbus_set_response_timeout(ctx, (uint32_t)(ms / 1000), (uint32_t)(ms % 1000) * 1000);
    }
    modbus_mapping_t *map = modbus_mapping_new(16, 16, 16, 16);
    if (map == NULL) {
        fprintf(stderr, "rtu_slave: no memory\n");
        return 2;
    }
    for (int i = 0; i < 16; i++) {
        map->tab_input_registers[i] = (uint16_t)(100 + i);
        map->tab_registers[i] = (uint16_t)(1000 + i);
    }
    if (modbus_connect(ctx) == -1) {
        fprintf(stderr, "rtu_slave: cannot open %s: %s\n", argv[1], modbus_strerror(errno));
        return 1;
    }
    modbus_flush(ctx);              /* a unit powering up has heard nothing before */
    printf("READY\n");
    fflush(stdout);
    uint8_t query[MODBUS_RTU_MAX_ADU_LENGTH];
    for (;;) {
        int rc = modbus_receive(ctx, query);
        if (rc == 0)
            continue;               /* a request for another unit, or a damaged one */
        if (rc < 0) {
            if (errno == EMBBADCRC || errno == EMBBADDATA || errno == EMBBADSLAVE)
                continue;
            fprintf(stderr, "rtu_slave: receive: %s\n", modbus_strerror(errno));
            break;
        }
        if (delay_ms > 0)
            usleep((useconds_t)(delay_ms * 1000));
        if (modbus_reply(ctx, query, rc, map) < 0) {
            fprintf(stderr, "rtu_slave: reply: %s\n", modbus_strerror(errno));
            continue;
        }
        printf("REQ %d HR", query[1]);
        for (int i = 0; i < 16; i++)
            printf(" %u", map->tab_registers[i]);
        printf(" CO ");
        for (int i = 0; i < 16; i++)
            printf("%d", map->tab_bits[i] ? 1 : 0);
        printf("\n");
        fflush(stdout);
    }
    modbus_mapping_free(map);
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}

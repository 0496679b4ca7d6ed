# arm.mk: the ARM targets of the board firmware, included at the end of firmware/Makefile
# (`-include targets/arm.mk`; make runs in firmware/). Uses $(CORE_SRC) from the Makefile.
#
#   make disc    STM32F407 Discovery image (LIS3DSH on SPI1, USART2 station link, flash NVM);
#                prints arm-none-eabi-size and the flash/RAM use (also in build/disc/size.txt)
#   make qemu    the emulated board for qemu-system-arm -M netduinoplus2 -> build/qemu/fw.elf
#   make bench   instructions per sample under QEMU -icount shift=0 -> build/bench/bench.txt
#   make sizes   builds every ARM image (disc, qemu, bench) and prints flash (text+data) and RAM
#                (data+bss) of each (also in build/sizes.txt)
#
# Every ARM variable is ARM_* / DISC_* / QEMU_* / BENCH_* so nothing collides with the host rules.

ARM_CC      ?= arm-none-eabi-gcc
ARM_SIZE    ?= arm-none-eabi-size
ARM_QEMU    ?= qemu-system-arm
ARM_ARCH     = -mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard
ARM_CFLAGS   = $(ARM_ARCH) --specs=nano.specs -std=c99 -Wall -Wextra -Werror -Wshadow -Wdouble-promotion \
               -Os -g -ffunction-sections -fdata-sections -fno-common \
               -Icore -Idrivers -Itargets/stm32f407disc -Itargets/qemu
ARM_LDFLAGS  = -nostartfiles -Wl,--gc-sections -Wl,--no-warn-rwx-segments -Ttargets/stm32f407disc/stm32f4.ld
ARM_LIBS     = -lm -lc_nano -lgcc
ARM_STARTUP  = targets/stm32f407disc/startup_stm32f4.c
ARM_DEPS     = $(wildcard core/*.c core/*.h drivers/*.c drivers/*.h targets/stm32f407disc/*.c \
               targets/stm32f407disc/*.h targets/stm32f407disc/*.ld targets/qemu/*.c targets/qemu/*.h) \
               targets/arm.mk

# Flash budget of the CI size check: the code area is sectors 0-1 (vectors) + 4..11, 960 KB + 32 KB.
ARM_FLASH_KB = 992
ARM_RAM_KB   = 128

DISC_DIR = $(BUILD)/disc
DISC_SRC = $(ARM_STARTUP) $(wildcard targets/stm32f407disc/*.c) drivers/lis3dsh.c $(CORE_SRC)
DISC_SRC := $(sort $(DISC_SRC))

QEMU_DIR = $(BUILD)/qemu
QEMU_SRC = $(ARM_STARTUP) targets/qemu/main.c targets/qemu/semihost.c $(CORE_SRC)

BENCH_DIR = $(BUILD)/bench
BENCH_SRC = $(ARM_STARTUP) targets/qemu/bench.c targets/qemu/semihost.c $(CORE_SRC)
BENCH_N  ?= 20000

.PHONY: disc qemu bench sizes

# The size report runs every time (CI greps it), the link only when a source changed.
disc: $(DISC_DIR)/fw.elf
	@$(ARM_SIZE) $<
	@$(ARM_SIZE) $< | awk -v fk=$(ARM_FLASH_KB) -v rk=$(ARM_RAM_KB) 'NR==2 { \
	  printf "disc flash: %d bytes (%.1f KB of %d KB, text+data)\n", $$1+$$2, ($$1+$$2)/1024, fk; \
	  printf "disc RAM: %d bytes (%.1f KB of %d KB, data+bss; the stack takes the rest)\n", $$2+$$3, ($$2+$$3)/1024, rk }' \
	  | tee $(DISC_DIR)/size.txt

$(DISC_DIR)/fw.elf: $(ARM_DEPS)
	@mkdir -p $(DISC_DIR)
	$(ARM_CC) $(ARM_CFLAGS) -DFW_TARGET_DISC $(DISC_SRC) $(ARM_LDFLAGS) -Wl,-Map=$(DISC_DIR)/fw.map $(ARM_LIBS) -o $@

qemu: $(QEMU_DIR)/fw.elf
	@$(ARM_SIZE) $<

$(QEMU_DIR)/fw.elf: $(ARM_DEPS)
	@mkdir -p $(QEMU_DIR)
	$(ARM_CC) $(ARM_CFLAGS) -DFW_TARGET_QEMU $(QEMU_SRC) $(ARM_LDFLAGS) -Wl,-Map=$(QEMU_DIR)/fw.map $(ARM_LIBS) -o $@

$(BENCH_DIR)/bench.elf: $(ARM_DEPS)
	@mkdir -p $(BENCH_DIR)
	$(ARM_CC) $(ARM_CFLAGS) -DFW_TARGET_QEMU -DBENCH_N=$(BENCH_N) $(BENCH_SRC) $(ARM_LDFLAGS) \
	  -Wl,-Map=$(BENCH_DIR)/bench.map $(ARM_LIBS) -o $@

# -icount shift=0: every guest instruction advances QEMU's virtual clock by exactly 1 ns; the
# guest reads that clock through TIM2 and SysTick (method in targets/qemu/README.md).
bench: $(BENCH_DIR)/bench.elf
	@cd $(BENCH_DIR) && rm -f nvm.bin && timeout 300 $(ARM_QEMU) -M netduinoplus2 -nographic -monitor none \
	  -icount shift=0 -serial null -serial null -semihosting-config enable=on,target=native \
	  -kernel bench.elf > bench.txt 2>&1; rc=$$?; cat bench.txt; \
	  if [ $$rc -ne 0 ] || ! grep -q '^bench: instructions per sample' bench.txt; then \
	    echo "bench failed (rc $$rc)"; exit 1; fi

# flash = text + data (the initialised data is stored in flash too), RAM = data + bss (the stack and
# the rest of the 128 KB are not counted). One line per image, greppable.
sizes: $(DISC_DIR)/fw.elf $(QEMU_DIR)/fw.elf $(BENCH_DIR)/bench.elf
	@for elf in $^; do $(ARM_SIZE) $$elf | awk -v f=$$elf 'NR==2 { \
	  printf "size %-26s flash %6d B (text %d + data %d), RAM %6d B (data %d + bss %d)\n", \
	  f, $$1+$$2, $$1, $$2, $$2+$$3, $$2, $$3 }'; done | tee $(BUILD)/sizes.txt

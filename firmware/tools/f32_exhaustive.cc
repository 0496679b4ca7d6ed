// f32_exhaustive.cc: one-off check of fw_fmt_f32 (core/fw_num.c) over ALL 2^32 float32 bit patterns.
//
// Reference: the C++17 std::to_chars(float) of libstdc++ (shortest round-trip digits, nearest among
// the shortest, ties to even: the same choice numpy's Dragon4 "unique" mode makes), reformatted
// positionally here like numpy.format_float_positional(..., unique=True, trim="-"): "nan", "inf",
// "-inf", "0", "-0", digits with the point inside, "0.000ddd", "ddd000". Every bit pattern whose
// text differs is written to the mismatch file (one hex pattern per line), so a script can ask numpy
// itself about exactly those (tests/ or by hand); the count is printed. Also checked: nothing is
// written past the FW_F32_TEXT_MAX bytes fw_fmt_f32 may use (16 guard bytes after them), and the
// longest text is printed (it must stay below FW_F32_TEXT_MAX).
//
//   gcc -std=c99 -O2 -Ifirmware/core -c firmware/core/fw_num.c -o /tmp/fw_num.o
//   g++ -O2 -std=c++17 -pthread -Ifirmware/core firmware/tools/f32_exhaustive.cc /tmp/fw_num.o -o /tmp/f32_exhaustive
//   /tmp/f32_exhaustive [threads] [mismatch-file]      (2 threads: about 5 minutes)
#include <charconv>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <thread>
#include <vector>
#include <mutex>

extern "C" {
#include "fw_num.h"
}

static std::string reference(uint32_t bits)
{
    float v;
    std::memcpy(&v, &bits, 4);
    uint32_t mag = bits & 0x7FFFFFFFu;
    if (mag > 0x7F800000u) return "nan";
    std::string sign = (bits >> 31) ? "-" : "";
    if (mag == 0x7F800000u) return sign + "inf";
    if (mag == 0) return sign + "0";
    char buf[64];
    auto r = std::to_chars(buf, buf + sizeof buf, v < 0 ? -v : v, std::chars_format::scientific);
    *r.ptr = 0;
    // d[.ddd]e[+-]XX
    std::string digits;
    const char *p = buf;
    while (*p != 'e') {
        if (*p != '.') digits += *p;
        p++;
    }
    int e = std::atoi(p + 1);
    while (digits.size() > 1 && digits.back() == '0') digits.pop_back();
    int point = e + 1;   // digits before the decimal point
    int nd = (int)digits.size();
    std::string out;
    if (point <= 0) out = "0." + std::string(-point, '0') + digits;
    else if (point < nd) out = digits.substr(0, point) + "." + digits.substr(point);
    else out = digits + std::string(point - nd, '0');
    return sign + out;
}

int main(int argc, char **argv)
{
    unsigned nthreads = argc > 1 ? (unsigned)std::atoi(argv[1]) : 2u;
    const char *mfile = argc > 2 ? argv[2] : "/tmp/f32_mismatch.txt";
    FILE *mf = std::fopen(mfile, "w");
    std::mutex mu;
    std::vector<uint64_t> bad(nthreads, 0);
    std::vector<uint32_t> longest(nthreads, 0);
    std::vector<std::thread> th;
    const uint64_t total = 1ull << 32;
    for (unsigned t = 0; t < nthreads; t++) {
        th.emplace_back([&, t] {
            char mine[FW_F32_TEXT_MAX + 16];
            std::memset(mine, 0x5A, sizeof mine);
            for (uint64_t i = t; i < total; i += nthreads) {
                uint32_t bits = (uint32_t)i;
                float v;
                std::memcpy(&v, &bits, 4);
                uint32_t n = fw_fmt_f32(mine, v);
                std::string want = reference(bits);
                bool guard_ok = true;
                for (uint32_t g = FW_F32_TEXT_MAX; g < sizeof mine; g++) guard_ok = guard_ok && mine[g] == 0x5A;
                if (n > longest[t]) longest[t] = n;
                if (!guard_ok || n != want.size() || std::memcmp(mine, want.data(), n) != 0 || mine[n] != 0) {
                    std::lock_guard<std::mutex> g(mu);
                    if (bad[t] < 20) std::printf("mismatch %08X: C \"%s\" reference \"%s\"\n", bits, mine, want.c_str());
                    std::fprintf(mf, "%08X\n", bits);
                    bad[t]++;
                }
            }
        });
    }
    for (auto &x : th) x.join();
    std::fclose(mf);
    uint64_t nbad = 0;
    uint32_t nlong = 0;
    for (auto b : bad) nbad += b;
    for (auto l : longest) nlong = l > nlong ? l : nlong;
    std::printf("f32_exhaustive: %llu bit patterns, %llu mismatches (list in %s), longest text %u characters\n",
                (unsigned long long)total, (unsigned long long)nbad, mfile, nlong);
    return nbad ? 1 : 0;
}

/* cpuid_mask: an LD_PRELOAD library that makes a process see a smaller x86 CPU class.
 *
 * Built and used by msfnet.bench.cpu_proxy (see there for why). On load, when MSFNET_CPU_PROXY
 * names a class, it asks Linux to make the cpuid instruction fault in this process
 * (arch_prctl ARCH_SET_CPUID; needs CPUID faulting, /proc/cpuinfo flag "cpuid_fault") and answers
 * each faulting cpuid from a SIGSEGV handler: the real answer with the class's missing feature
 * bits cleared. Every library (numpy, ONNX Runtime's MLAS, oneDNN in OpenVINO and torch) then
 * picks the kernels it would pick on that class. The setting is per thread and inherited by new
 * threads; a child process re-loads this library through the inherited LD_PRELOAD.
 *
 * Other code may install its own SIGSEGV handler (Python's faulthandler does): sigaction() and
 * signal() are wrapped so that such a handler is kept aside and called for real faults, while
 * this one stays in place for cpuid. A thread that blocks every signal would die at its first
 * cpuid, so sigprocmask() and pthread_sigmask() never block SIGSEGV. The handler runs on the
 * alternate stack where one is set (a stack overflow still reaches faulthandler).
 *
 * Not covered: the dynamic loader reads cpuid before this library loads, so glibc's own string
 * routines keep the variants of the real CPU (they are no part of what is measured here).
 */
#define _GNU_SOURCE
#include <asm/prctl.h>
#include <cpuid.h>
#include <dlfcn.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <ucontext.h>
#include <unistd.h>

enum proxy_class { FULL, AVX2_ONLY, AVX2_VNNI, AVX512_VNNI };
static enum proxy_class proxy = FULL;

typedef int (*sigaction_fn)(int, const struct sigaction *, struct sigaction *);
typedef int (*sigmask_fn)(int, const sigset_t *, sigset_t *);
static sigaction_fn real_sigaction;
static struct sigaction chained; /* the handler other code asked for (SIG_DFL until then) */

#define BIT(n) (1u << (n))

/* Leaf 7 sub-leaf 0: EBX AVX-512 F/DQ/IFMA/PF/ER/CD/BW/VL; ECX VBMI/VBMI2/VNNI/BITALG/VPOPCNTDQ;
 * EDX 4VNNIW/4FMAPS/VP2INTERSECT, AMX-BF16, AVX512-FP16, AMX-TILE, AMX-INT8. */
static const unsigned AVX512_EBX = BIT(16) | BIT(17) | BIT(21) | BIT(26) | BIT(27) | BIT(28) |
                                   BIT(30) | BIT(31);
static const unsigned AVX512_ECX = BIT(1) | BIT(6) | BIT(11) | BIT(12) | BIT(14);
static const unsigned NEWER_EDX = BIT(2) | BIT(3) | BIT(8) | BIT(22) | BIT(23) | BIT(24) | BIT(25);
/* What a Cascade Lake has beyond AVX2: AVX-512 F/DQ/CD/BW/VL and VNNI */
static const unsigned CASCADE_EBX = BIT(16) | BIT(17) | BIT(28) | BIT(30) | BIT(31);
static const unsigned CASCADE_ECX = BIT(11);

static void mask(unsigned leaf, unsigned sub, unsigned r[4]) {
    if (leaf == 7 && sub == 0) {
        unsigned keep_ebx = proxy == AVX512_VNNI ? CASCADE_EBX : 0;
        unsigned keep_ecx = proxy == AVX512_VNNI ? CASCADE_ECX : 0;
        r[1] &= ~(AVX512_EBX & ~keep_ebx);
        r[2] &= ~(AVX512_ECX & ~keep_ecx);
        r[3] &= ~NEWER_EDX;
    } else if (leaf == 7 && sub == 1) {
        /* EAX: AVX-VNNI (bit 4), AVX512-BF16 (5), AMX-FP16, AVX-IFMA ...; EDX: AVX-VNNI-INT8 ... */
        r[0] &= proxy == AVX2_VNNI ? BIT(4) : 0;
        r[3] = 0;
    } else if (leaf == 0x1d || leaf == 0x1e || leaf == 0x24) { /* AMX tiles, AVX10 */
        r[0] = r[1] = r[2] = r[3] = 0;
    }
}

static void on_segv(int sig, siginfo_t *info, void *context) {
    ucontext_t *uc = context;
    greg_t *g = uc->uc_mcontext.gregs;
    const unsigned char *ip = (const unsigned char *)g[REG_RIP];
    if (info->si_code == SI_KERNEL && ip[0] == 0x0f && ip[1] == 0xa2) {
        unsigned leaf = (unsigned)g[REG_RAX], sub = (unsigned)g[REG_RCX], r[4];
        syscall(SYS_arch_prctl, ARCH_SET_CPUID, 1); /* this thread only, for one real cpuid */
        __cpuid_count(leaf, sub, r[0], r[1], r[2], r[3]);
        syscall(SYS_arch_prctl, ARCH_SET_CPUID, 0);
        mask(leaf, sub, r);
        g[REG_RAX] = r[0];
        g[REG_RBX] = r[1];
        g[REG_RCX] = r[2];
        g[REG_RDX] = r[3];
        g[REG_RIP] += 2;
        return;
    }
    /* A real fault: whatever handler the program installed, else the default (re-faults, dies) */
    if (chained.sa_flags & SA_SIGINFO) {
        chained.sa_sigaction(sig, info, context);
    } else if (chained.sa_handler != SIG_DFL && chained.sa_handler != SIG_IGN) {
        chained.sa_handler(sig);
    } else {
        struct sigaction dfl;
        memset(&dfl, 0, sizeof dfl);
        dfl.sa_handler = SIG_DFL;
        real_sigaction(sig, &dfl, NULL);
        /* sent by kill() / tgkill() / sigqueue(): there is no fault to run again, so send it
           again; it is blocked in here and arrives, default and fatal, on return */
        if (info->si_code <= 0) raise(sig);
    }
}

int sigaction(int sig, const struct sigaction *act, struct sigaction *old) {
    if (!real_sigaction) real_sigaction = (sigaction_fn)dlsym(RTLD_NEXT, "sigaction");
    if (proxy == FULL || sig != SIGSEGV) return real_sigaction(sig, act, old);
    if (old) *old = chained;
    if (act) chained = *act;
    return 0;
}

/* Blocking SIGSEGV would turn the next cpuid into a kill: it stays deliverable */
static int masked(sigmask_fn real, int how, const sigset_t *set, sigset_t *old) {
    if (proxy == FULL || set == NULL || how == SIG_UNBLOCK) return real(how, set, old);
    sigset_t copy = *set;
    sigdelset(&copy, SIGSEGV);
    return real(how, &copy, old);
}

int sigprocmask(int how, const sigset_t *set, sigset_t *old) {
    static sigmask_fn real;
    if (!real) real = (sigmask_fn)dlsym(RTLD_NEXT, "sigprocmask");
    return masked(real, how, set, old);
}

int pthread_sigmask(int how, const sigset_t *set, sigset_t *old) {
    static sigmask_fn real;
    if (!real) real = (sigmask_fn)dlsym(RTLD_NEXT, "pthread_sigmask");
    return masked(real, how, set, old);
}

sighandler_t signal(int sig, sighandler_t handler) {
    struct sigaction act, old;
    memset(&act, 0, sizeof act);
    act.sa_handler = handler;
    act.sa_flags = SA_RESTART;
    if (sigaction(sig, &act, &old) != 0) return SIG_ERR;
    return old.sa_handler;
}

__attribute__((constructor)) static void install(void) {
    const char *name = getenv("MSFNET_CPU_PROXY");
    if (!real_sigaction) real_sigaction = (sigaction_fn)dlsym(RTLD_NEXT, "sigaction");
    if (!name) return;
    if (!strcmp(name, "avx2")) proxy = AVX2_ONLY;
    else if (!strcmp(name, "avx2_vnni")) proxy = AVX2_VNNI;
    else if (!strcmp(name, "avx512_vnni")) proxy = AVX512_VNNI;
    else {
        fprintf(stderr, "cpuid_mask: MSFNET_CPU_PROXY=%s: unknown class\n", name);
        _exit(2);
    }
    memset(&chained, 0, sizeof chained);
    chained.sa_handler = SIG_DFL;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = on_segv;
    sa.sa_flags = SA_SIGINFO | SA_NODEFER | SA_ONSTACK;
    real_sigaction(SIGSEGV, &sa, NULL);
    if (syscall(SYS_arch_prctl, ARCH_SET_CPUID, 0) != 0) {
        perror("cpuid_mask: arch_prctl(ARCH_SET_CPUID)");
        _exit(2);
    }
}

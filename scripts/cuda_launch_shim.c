// LD_PRELOAD shim (scripts/launch_shim.py builds and runs it): times every cuGraphLaunch the process makes (XLA looks
// the driver's entry points up by dlsym), counts the kernel nodes XLA updates in an instantiated graph before each
// launch (cuGraphExecKernelNodeSetParams), and writes the first 40 graphs instantiated as DOT files
// (cuGraphDebugDotPrint). Log lines in $SHIM_DIR/shim.log: "launch EXEC HOST_US START_US NODE_UPDATES" and
// "instantiate EXEC flags FLAGS".
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef int (*launch_t)(void*, void*);
typedef int (*inst_t)(void*, void*, unsigned long long);
typedef int (*dot_t)(void*, const char*, unsigned int);
typedef int (*set_t)(void*, void*, const void*);
static void* (*real_dlsym)(void*, const char*);
static launch_t real_launch;
static inst_t real_inst;
static dot_t dot_print;
static set_t real_set, real_set_v2;
static long node_updates;   // kernel nodes whose parameters were set in an instantiated graph since the last launch
static int dumped;
static FILE* log_file;

// CLOCK_MONOTONIC, the clock of Python's time.perf_counter on Linux
static double now_us(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec * 1e6 + t.tv_nsec / 1e3;
}

static int my_launch(void* exec, void* stream) {
  double t0 = now_us(); int r = real_launch(exec, stream); double t1 = now_us();
  if (log_file) {
    fprintf(log_file, "launch %p %.2f %.2f %ld\n", exec, t1 - t0, t0, node_updates);
    fflush(log_file);
  }
  node_updates = 0;
  return r;
}

static int my_inst(void* exec, void* graph, unsigned long long flags) {
  int r = real_inst(exec, graph, flags);
  if (log_file) fprintf(log_file, "instantiate %p flags %llu\n", *(void**)exec, flags);
  if (dot_print && dumped < 40) {
    char path[512]; snprintf(path, sizeof path, "%s/graph_%02d_%p.dot", getenv("SHIM_DIR"), dumped++, *(void**)exec);
    dot_print(graph, path, 1u << 0 | 1u << 2 | 1u << 3);   // verbose, kernel node params, memcpy/memset params
  }
  return r;
}

static int my_set(void* exec, void* node, const void* params) { ++node_updates; return real_set(exec, node, params); }
static int my_set_v2(void* exec, void* node, const void* params) {
  ++node_updates;
  return real_set_v2(exec, node, params);
}

void* dlsym(void* handle, const char* name) {
  if (!real_dlsym) real_dlsym = dlvsym(RTLD_NEXT, "dlsym", "GLIBC_2.2.5");
  void* p = real_dlsym(handle, name);
  if (!log_file && getenv("SHIM_DIR")) {
    char path[512]; snprintf(path, sizeof path, "%s/shim.log", getenv("SHIM_DIR")); log_file = fopen(path, "w");
  }
  if (!p) return p;
  if (!strcmp(name, "cuGraphLaunch")) { real_launch = (launch_t)p; return (void*)my_launch; }
  if (!strcmp(name, "cuGraphExecKernelNodeSetParams")) { real_set = (set_t)p; return (void*)my_set; }
  if (!strcmp(name, "cuGraphExecKernelNodeSetParams_v2")) { real_set_v2 = (set_t)p; return (void*)my_set_v2; }
  if (!strcmp(name, "cuGraphInstantiateWithFlags")) {
    real_inst = (inst_t)p; dot_print = (dot_t)real_dlsym(handle, "cuGraphDebugDotPrint"); return (void*)my_inst;
  }
  return p;
}

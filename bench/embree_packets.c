/* Times Embree's 16-wide ray packets (rtcIntersect16 / rtcOccluded16) and, for reference, its single-ray calls
 * (rtcIntersect1 / rtcOccluded1) on one thread, over the buffers that rayd's trace_mesh example exports, and
 * checks that the packets find what rayd found (hit or miss, ray by ray). bench/compare_embree.py builds and runs
 * it against the Embree library that the embreex wheel ships (which comes without headers: the few declarations
 * used are below, as Embree 4's rtcore headers define them).
 *
 *     embree_packets DIR REPEAT closest|any THREADS [WIDTH]
 *
 * DIR holds vertices.f32, indices.u32, rays.bin (origin_tmin_direction_tmax, 32 bytes a ray) and hits.bin
 * (rayd's t_triid_u_v records, 16 bytes a ray). Packets are 16 consecutive rays of the buffer, the order rayd
 * gets them in; with WIDTH (the rays being an image's pixels, row by row, WIDTH a row, both sides multiples of 4)
 * also 4×4 tiles of pixels, Embree's best case. THREADS threads trace each batch together, taking chunks of
 * 1,024 rays (of the way's order) from a shared counter, as rayd's chunks are shared out; with 1 the calling
 * thread traces alone. Prints one line of JSON: M rays/s of the median of REPEAT traces each way, and the hit/miss
 * agreement of each way with rayd. With EMBREE_ROBUST=1 in the environment the scene is built with Embree's robust
 * (watertight) flag, as rayd's triangle test is; compare_embree.py does not set it. */

#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct RTCDeviceTy *RTCDevice;
typedef struct RTCSceneTy *RTCScene;
typedef struct RTCGeometryTy *RTCGeometry;

enum { RTC_GEOMETRY_TYPE_TRIANGLE = 0 };
enum { RTC_BUFFER_TYPE_INDEX = 0, RTC_BUFFER_TYPE_VERTEX = 1 };
enum { RTC_FORMAT_UINT3 = 0x5003, RTC_FORMAT_FLOAT3 = 0x9003 };
#define RTC_INVALID_GEOMETRY_ID ((unsigned int)-1)
#define LANES 16
#define CHUNK_RAYS 1024 /* rays a thread takes at once; a multiple of LANES */

struct RTCRay {
    float org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar;
    unsigned int mask, id, flags;
};
struct RTCHit {
    float Ng_x, Ng_y, Ng_z, u, v;
    unsigned int primID, geomID, instID[1], instPrimID[1];
};
struct RTCRayHit {
    struct RTCRay ray;
    struct RTCHit hit;
} __attribute__((aligned(16)));

struct RTCRay16 {
    float org_x[LANES], org_y[LANES], org_z[LANES], tnear[LANES];
    float dir_x[LANES], dir_y[LANES], dir_z[LANES], time[LANES];
    float tfar[LANES];
    unsigned int mask[LANES], id[LANES], flags[LANES];
} __attribute__((aligned(64)));
struct RTCHit16 {
    float Ng_x[LANES], Ng_y[LANES], Ng_z[LANES], u[LANES], v[LANES];
    unsigned int primID[LANES], geomID[LANES], instID[1][LANES], instPrimID[1][LANES];
} __attribute__((aligned(64)));
struct RTCRayHit16 {
    struct RTCRay16 ray;
    struct RTCHit16 hit;
} __attribute__((aligned(64)));

RTCDevice rtcNewDevice(const char *config);
int rtcGetDeviceError(RTCDevice device);
RTCScene rtcNewScene(RTCDevice device);
RTCGeometry rtcNewGeometry(RTCDevice device, int type);
void *rtcSetNewGeometryBuffer(RTCGeometry geometry, int type, unsigned int slot, int format, size_t stride,
                              size_t count);
void rtcCommitGeometry(RTCGeometry geometry);
unsigned int rtcAttachGeometry(RTCScene scene, RTCGeometry geometry);
void rtcReleaseGeometry(RTCGeometry geometry);
void rtcCommitScene(RTCScene scene);
void rtcSetSceneFlags(RTCScene scene, int flags); /* enum RTCSceneFlags */
void rtcIntersect1(RTCScene scene, struct RTCRayHit *rayhit, void *args);
void rtcOccluded1(RTCScene scene, struct RTCRay *ray, void *args);
void rtcIntersect16(const int *valid, RTCScene scene, struct RTCRayHit16 *rayhit, void *args);
void rtcOccluded16(const int *valid, RTCScene scene, struct RTCRay16 *ray, void *args);

/* The whole of file DIR/NAME, its length in *len. */
static void *load(const char *dir, const char *name, size_t *len) {
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *f = fopen(path, "rb");
    if (!f) { perror(path); exit(2); }
    fseek(f, 0, SEEK_END);
    *len = (size_t)ftell(f);
    fseek(f, 0, SEEK_SET);
    void *data = malloc(*len ? *len : 1);
    if (fread(data, 1, *len, f) != *len) { fprintf(stderr, "%s: short read\n", path); exit(2); }
    fclose(f);
    return data;
}

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static int by_value(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* Rays as exported: origin, tmin, direction, tmax. */
typedef struct { float o[3], tmin, d[3], tmax; } Ray;

/* Traces rays first .. first + count (of `order`: the rays in packet order, 16 a packet) in packets of 16, or one
 * by one (`order` NULL), closest or any hit; hit[i] = 1 where ray i hits. */
static void trace_range(RTCScene scene, const Ray *rays, size_t first, size_t count, const size_t *order, int any,
                        unsigned char *hit) {
    size_t end = first + count;
    if (!order) {
        for (size_t i = first; i < end; i++) {
            struct RTCRayHit rh;
            const Ray *r = &rays[i];
            rh.ray = (struct RTCRay){r->o[0], r->o[1], r->o[2], r->tmin, r->d[0], r->d[1], r->d[2],
                                     0.0f, r->tmax, 0xffffffffu, 0, 0};
            rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
            if (any) {
                rtcOccluded1(scene, &rh.ray, NULL);
                hit[i] = rh.ray.tfar == -INFINITY;
            } else {
                rtcIntersect1(scene, &rh, NULL);
                hit[i] = rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
            }
        }
        return;
    }
    /* Generous room after the packet: Embree may know more hit fields than declared here. */
    struct { struct RTCRayHit16 rh; char spare[4096]; } p __attribute__((aligned(64)));
    for (size_t at = first; at < end; at += LANES) {
        int valid[LANES];
        for (int l = 0; l < LANES; l++) {
            valid[l] = at + l < end ? -1 : 0;
            const Ray *r = &rays[order[at + l < end ? at + l : at]];
            p.rh.ray.org_x[l] = r->o[0], p.rh.ray.org_y[l] = r->o[1], p.rh.ray.org_z[l] = r->o[2];
            p.rh.ray.dir_x[l] = r->d[0], p.rh.ray.dir_y[l] = r->d[1], p.rh.ray.dir_z[l] = r->d[2];
            p.rh.ray.tnear[l] = r->tmin, p.rh.ray.tfar[l] = r->tmax, p.rh.ray.time[l] = 0.0f;
            p.rh.ray.mask[l] = 0xffffffffu, p.rh.ray.id[l] = 0, p.rh.ray.flags[l] = 0;
            p.rh.hit.geomID[l] = RTC_INVALID_GEOMETRY_ID;
        }
        if (any) rtcOccluded16(valid, scene, &p.rh.ray, NULL);
        else rtcIntersect16(valid, scene, &p.rh, NULL);
        for (int l = 0; l < LANES && at + l < end; l++)
            hit[order[at + l]] = any ? p.rh.ray.tfar[l] == -INFINITY : p.rh.hit.geomID[l] != RTC_INVALID_GEOMETRY_ID;
    }
}

/* One trace of a whole batch, shared by its threads: each takes the next CHUNK_RAYS rays until none are left. */
typedef struct {
    RTCScene scene;
    const Ray *rays;
    size_t n;
    const size_t *order;
    int any;
    unsigned char *hit;
    atomic_size_t next;
} Batch;

static void *trace_chunks(void *arg) {
    Batch *b = arg;
    for (;;) {
        size_t first = atomic_fetch_add(&b->next, CHUNK_RAYS);
        if (first >= b->n) return NULL;
        trace_range(b->scene, b->rays, first, b->n - first < CHUNK_RAYS ? b->n - first : CHUNK_RAYS, b->order,
                    b->any, b->hit);
    }
}

/* Traces every ray with `threads` threads (the calling one among them). */
static void trace(RTCScene scene, const Ray *rays, size_t n, const size_t *order, int any, int threads,
                  unsigned char *hit) {
    Batch batch = {scene, rays, n, order, any, hit, 0};
    pthread_t helpers[threads > 1 ? threads - 1 : 1];
    for (int k = 0; k < threads - 1; k++) {
        if (pthread_create(&helpers[k], NULL, trace_chunks, &batch)) { fprintf(stderr, "pthread_create\n"); exit(1); }
    }
    trace_chunks(&batch);
    for (int k = 0; k < threads - 1; k++) pthread_join(helpers[k], NULL);
}

/* Median M rays/s of `repeat` traces. */
static double speed(RTCScene scene, const Ray *rays, size_t n, const size_t *order, int any, int threads, int repeat,
                    unsigned char *hit) {
    double *times = malloc(sizeof(double) * (size_t)repeat);
    for (int k = 0; k < repeat; k++) {
        double start = now_s();
        trace(scene, rays, n, order, any, threads, hit);
        times[k] = now_s() - start;
    }
    qsort(times, (size_t)repeat, sizeof(double), by_value);
    double median = times[repeat / 2];
    free(times);
    return n / median / 1e6;
}

/* Hit/miss agreement, in percent, of `hit` with rayd's t_triid_u_v records `rayd_hits`. */
static double agreement(const unsigned char *rayd_hits, const unsigned char *hit, size_t n) {
    size_t agree = 0;
    for (size_t i = 0; i < n; i++) {
        uint32_t prim;
        memcpy(&prim, rayd_hits + 16 * i + 4, 4);
        agree += (prim != 0xffffffffu) == hit[i];
    }
    return 100.0 * agree / n;
}

int main(int argc, char **argv) {
    if (argc < 5 || argc > 6 || (strcmp(argv[3], "closest") && strcmp(argv[3], "any")) || atoi(argv[4]) < 1) {
        fprintf(stderr, "usage: %s DIR REPEAT closest|any THREADS [WIDTH]\n", argv[0]);
        return 2;
    }
    int threads = atoi(argv[4]);
    size_t width = argc == 6 ? (size_t)atol(argv[5]) : 0;
    const char *dir = argv[1];
    int repeat = atoi(argv[2]), any = !strcmp(argv[3], "any");
    if (repeat < 1) repeat = 1;
    size_t vlen, ilen, rlen, hlen;
    float *vertices = load(dir, "vertices.f32", &vlen);
    uint32_t *indices = load(dir, "indices.u32", &ilen);
    Ray *rays = load(dir, "rays.bin", &rlen);
    unsigned char *rayd_hits = load(dir, "hits.bin", &hlen);
    size_t n = rlen / sizeof(Ray);
    if (hlen != n * 16) { fprintf(stderr, "hits.bin: expected 16 bytes a ray\n"); return 2; }

    RTCDevice device = rtcNewDevice("threads=1");
    RTCScene scene = rtcNewScene(device);
    RTCGeometry mesh = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    float *v = rtcSetNewGeometryBuffer(mesh, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 12, vlen / 12);
    uint32_t *t = rtcSetNewGeometryBuffer(mesh, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 12, ilen / 12);
    memcpy(v, vertices, vlen);
    memcpy(t, indices, ilen);
    rtcCommitGeometry(mesh);
    rtcAttachGeometry(scene, mesh);
    rtcReleaseGeometry(mesh);
    /* EMBREE_ROBUST=1: RTC_SCENE_FLAG_ROBUST (1 << 2), Embree's watertight mode, as rayd's triangle test is. */
    const char *robust = getenv("EMBREE_ROBUST");
    if (robust && !strcmp(robust, "1")) rtcSetSceneFlags(scene, 1 << 2);
    rtcCommitScene(scene);
    if (rtcGetDeviceError(device)) { fprintf(stderr, "Embree error %d\n", rtcGetDeviceError(device)); return 1; }

    unsigned char *hit = malloc(n);
    double single_agreement, packet_agreement, tile_agreement = 0.0, tiles = 0.0;
    double single = speed(scene, rays, n, NULL, any, threads, repeat, hit);
    single_agreement = agreement(rayd_hits, hit, n);
    size_t *order = calloc(n, sizeof(size_t));
    for (size_t i = 0; i < n; i++) order[i] = i;
    double packets = speed(scene, rays, n, order, any, threads, repeat, hit);
    packet_agreement = agreement(rayd_hits, hit, n);
    if (width) {
        size_t height = n / width;
        if (width % 4 || height % 4 || width * height != n) { fprintf(stderr, "WIDTH: no 4×4 tiles\n"); return 2; }
        size_t k = 0;
        for (size_t ty = 0; ty < height; ty += 4)
            for (size_t tx = 0; tx < width; tx += 4)
                for (size_t dy = 0; dy < 4; dy++)
                    for (size_t dx = 0; dx < 4; dx++) order[k++] = (ty + dy) * width + tx + dx;
        tiles = speed(scene, rays, n, order, any, threads, repeat, hit);
        tile_agreement = agreement(rayd_hits, hit, n);
    }
    printf("{\"rays\": %zu, \"single_mrays_per_s\": %.3f, \"packet_mrays_per_s\": %.3f, "
           "\"tile_mrays_per_s\": %.3f, \"single_agreement\": %.6f, \"packet_agreement\": %.6f, "
           "\"tile_agreement\": %.6f}\n",
           n, single, packets, tiles, single_agreement, packet_agreement, tile_agreement);
    return 0;
}

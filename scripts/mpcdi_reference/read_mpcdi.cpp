// A reader of .mpcdi files built against the reference MPCDI library (Scalable Display Technologies, BSD; not part
// of this repository: scripts/check_mpcdi_reference.sh clones and builds it). Prints what the library read, one
// "key value..." a line: the profile, level and date; per buffer its resolution; per region its box, resolution,
// frustum and coordinate frame, the warp's attributes and every sample (row by row in the library's own (x, y)
// indexing), the alpha and beta maps' size and every value, the distortion map's every sample.
// scripts/check_mpcdi_reference.py compares all of it with what ProCam wrote.
//
// Usage: read_mpcdi FILE.mpcdi [--any-version] [--validate]
//   --any-version: the reader's CheckVersionSupported off (by default, as nDisplay calls it, the library refuses a
//   file whose version's major number is above 1).
//   --validate: the reader's DoProfileValidation on (off by default, and in nDisplay): Profile::ValidateProfile.
#include <cstdio>
#include <cstring>
#include <string>

#include "mpcdiErrorHelper.h"
#include "mpcdiProfile.h"
#include "mpcdiReader.h"

static void pfmRows(const std::string &p, mpcdi::PFM *w) {
  unsigned int xs = w->GetSizeX(), ys = w->GetSizeY();
  std::printf("%s.xSamples %u\n%s.ySamples %u\n", p.c_str(), xs, p.c_str(), ys);
  for (unsigned int y = 0; y < ys; y++) {
    std::printf("%s.row[%u]", p.c_str(), y);
    for (unsigned int x = 0; x < xs; x++) {
      mpcdi::NODE n = (*w)(x, y);
      std::printf(" %.9g %.9g %.9g", n.r, n.g, n.b);
    }
    std::printf("\n");
  }
}

static void mapRows(const std::string &p, mpcdi::DataMap *m) {
  unsigned int w = m->GetSizeX(), h = m->GetSizeY(), c = m->GetComponentDepth();
  std::printf("%s.size %u %u %u\n%s.bitDepth %d\n", p.c_str(), w, h, c, p.c_str(), (int)m->GetBitDepth());
  for (unsigned int y = 0; y < h; y++) {
    std::printf("%s.row[%u]", p.c_str(), y);
    for (unsigned int x = 0; x < w; x++)
      for (unsigned int z = 0; z < c; z++) std::printf(" %d", (int)(*m)(x, y, z));
    std::printf("\n");
  }
}

int main(int argc, char **argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: %s FILE.mpcdi [--any-version] [--validate]\n", argv[0]);
    return 2;
  }
  mpcdi::Profile *profile = new mpcdi::Profile();
  mpcdi::Reader *reader = mpcdi::Reader::CreateReader();
  for (int i = 2; i < argc; i++) {
    if (std::strcmp(argv[i], "--any-version") == 0) reader->SetCheckVersionSupported(false);
    else if (std::strcmp(argv[i], "--validate") == 0) reader->SetDoProfileValidation(true);
    else {
      std::fprintf(stderr, "unknown option %s\n", argv[i]);
      return 2;
    }
  }
  mpcdi::MPCDI_Error err = reader->Read(argv[1], profile);
  delete reader;
  if (MPCDI_FAILED(err)) {
    std::printf("error %d %s\n", (int)err, mpcdi::ErrorHelper::GetLastError().c_str());
    return 1;
  }
  std::printf("profile %s\nlevel %d\ndate %s\n", mpcdi::GetProfileType(profile->GetProfileType()).c_str(),
              profile->GetLevel(), profile->GetDate().c_str());
  mpcdi::Display *d = profile->GetDisplay();
  for (auto b = d->GetBufferBegin(); b != d->GetBufferEnd(); ++b) {
    mpcdi::Buffer *buf = b->second;
    std::printf("buffer.%s.resolution %d %d\n", buf->GetId().c_str(), buf->GetXresolution(), buf->GetYresolution());
    for (auto r = buf->GetRegionBegin(); r != buf->GetRegionEnd(); ++r) {
      mpcdi::Region *reg = r->second;
      std::string p = "region." + reg->GetId();
      const char *P = p.c_str();
      std::printf("%s.buffer %s\n", P, buf->GetId().c_str());
      std::printf("%s.box %.9g %.9g %.9g %.9g\n", P, reg->GetX(), reg->GetY(), reg->GetXsize(), reg->GetYsize());
      std::printf("%s.resolution %d %d\n", P, reg->GetXresolution(), reg->GetYresolution());
      if (mpcdi::Frustum *f = reg->GetFrustum())
        std::printf("%s.frustum %.17g %.17g %.17g %.17g %.17g %.17g %.17g\n", P, f->GetYaw(), f->GetPitch(),
                    f->GetRoll(), f->GetRightAngle(), f->GetLeftAngle(), f->GetUpAngle(), f->GetDownAngle());
      if (mpcdi::CoordinateFrame *c = reg->GetCoordinateFrame())
        std::printf("%s.coordinateFrame %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g %.17g\n", P,
                    c->GetPosx(), c->GetPosy(), c->GetPosz(), c->GetYawx(), c->GetYawy(), c->GetYawz(),
                    c->GetPitchx(), c->GetPitchy(), c->GetPitchz(), c->GetRollx(), c->GetRolly(), c->GetRollz());
      mpcdi::FileSet *fs = reg->GetFileSet();
      if (mpcdi::GeometryWarpFile *w = fs->GetGeometryWarpFile()) {
        std::printf("%s.warp.path %s\n", P, w->GetPath().c_str());
        std::printf("%s.warp.geometricUnit %s\n", P, mpcdi::GetGeometricUnit(w->GetGeometricUnit()).c_str());
        std::printf("%s.warp.interpolation %s\n", P, mpcdi::GetInterpolation(w->GetInterpolation()).c_str());
        std::printf("%s.warp.originOf3DData %s\n", P, mpcdi::GetOriginOf3DData(w->GetOriginOf3DData()).c_str());
        pfmRows(p + ".warp", w);
      }
      if (mpcdi::AlphaMap *a = fs->GetAlphaMap()) mapRows(p + ".alpha", a);
      if (mpcdi::BetaMap *bm = fs->GetBetaMap()) mapRows(p + ".beta", bm);
      if (mpcdi::DistortionMap *dm = fs->GetDistortionMap()) pfmRows(p + ".distortion", dm);
    }
  }
  delete profile;
  return 0;
}

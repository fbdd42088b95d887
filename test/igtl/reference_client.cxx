// A Slicer stand-in built on the reference OpenIGTLink C++ library (Debian: libopenigtlink-dev),
// used by test_igtl_reference_client.py to check what the bridge sends.
//
//   reference_client [-p K] HOST PORT TIMEOUT_S TYPE:DEVICE[:COUNT]...
//
// Connects to HOST:PORT (retrying until TIMEOUT_S), reads messages until each expected
// TYPE:DEVICE has arrived COUNT times (default 1) or TIMEOUT_S has passed, unpacks every
// TRANSFORM, POLYDATA and STRING with the library's CRC check (Unpack(1) must return
// UNPACK_BODY) and prints one line per message: tab-separated key=value fields after "MSG",
// "text=" last (it may hold spaces). Points are "x,y,z" joined by ";", cells "a,b,c" likewise.
//
//   MSG type=TRANSFORM device=D version=1 crc=ok stamp=SEC,FRAC matrix=m00,m01,...,m33 (row-major)
//   MSG type=POLYDATA ... points=N vertices=V lines=L polygons=P strips=S attributes=A
//       polygon_words=W first_points=(first K points) point_sum=sx,sy,sz first_polygons=(first K)
//   MSG type=STRING ... encoding=MIBENUM text=...
//   MSG type=OTHER device=D name=TYPE        (any other type: body skipped)
//   DONE messages=M
//
// Exit status: 0 every expected message seen and every CRC matched; 2 a CRC mismatch (a
// CRC_FAIL line) or a bad header; 3 an expected message missing at the timeout or when the
// server hung up (MISSING lines); 4 no connection; 1 bad command line.
//
// Build (Debian's paths; the test finds them): g++ -std=c++11 -I/usr/include/openigtlink
//   reference_client.cxx -o reference_client -L/usr/lib -lOpenIGTLink -lpthread

#include <igtlClientSocket.h>
#include <igtlMessageHeader.h>
#include <igtlPolyDataMessage.h>
#include <igtlStringMessage.h>
#include <igtlTransformMessage.h>
#include <igtlOSUtil.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <list>
#include <map>
#include <string>

namespace {

int g_first = 4;  // points (and polygons) printed per POLYDATA: -p K

struct Expected {
  int wanted;
  int seen;
};

// The header's first field as sent (big-endian uint16), read from the received bytes.
unsigned int HeaderVersion(igtl::MessageBase* message) {
  const unsigned char* raw = static_cast<const unsigned char*>(message->GetPackPointer());
  return (static_cast<unsigned int>(raw[0]) << 8) | raw[1];
}

void PrintPrefix(const char* type, igtl::MessageBase* message, unsigned int version) {
  unsigned int sec = 0, frac = 0;
  message->GetTimeStamp(&sec, &frac);
  std::printf("MSG\ttype=%s\tdevice=%s\tversion=%u\tcrc=ok\tstamp=%u,%u", type, message->GetDeviceName(), version,
              sec, frac);
}

// 0 on success, 2 when the CRC does not match (or the body cannot be unpacked).
int Finish(igtl::MessageBase* message, const char* type) {
  int flags = message->Unpack(1);
  if (!(flags & igtl::MessageHeader::UNPACK_BODY)) {
    std::printf("CRC_FAIL\ttype=%s\tdevice=%s\n", type, message->GetDeviceName());
    std::fflush(stdout);
    return 2;
  }
  return 0;
}

int ReceiveBody(igtl::Socket* socket, igtl::MessageBase* message, igtl::MessageHeader* header) {
  message->SetMessageHeader(header);
  message->AllocatePack();
  int size = message->GetPackBodySize();
  if (size == 0) return 1;
  return socket->Receive(message->GetPackBodyPointer(), size) == size;
}

int Transform(igtl::Socket* socket, igtl::MessageHeader* header, unsigned int version) {
  igtl::TransformMessage::Pointer message = igtl::TransformMessage::New();
  if (!ReceiveBody(socket, message, header)) return -1;
  if (int rc = Finish(message, "TRANSFORM")) return rc;
  igtl::Matrix4x4 matrix;
  message->GetMatrix(matrix);
  PrintPrefix("TRANSFORM", message, version);
  std::printf("\tmatrix=");
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c) std::printf("%s%.9g", (r || c) ? "," : "", matrix[r][c]);
  std::printf("\n");
  return 0;
}

unsigned int CellCount(igtl::PolyDataCellArray* cells) { return cells ? cells->GetNumberOfCells() : 0; }

int PolyData(igtl::Socket* socket, igtl::MessageHeader* header, unsigned int version) {
  igtl::PolyDataMessage::Pointer message = igtl::PolyDataMessage::New();
  if (!ReceiveBody(socket, message, header)) return -1;
  if (int rc = Finish(message, "POLYDATA")) return rc;
  igtl::PolyDataPointArray* points = message->GetPoints();
  int n = points ? points->GetNumberOfPoints() : 0;
  igtl::PolyDataCellArray* polygons = message->GetPolygons();
  PrintPrefix("POLYDATA", message, version);
  std::printf("\tpoints=%d\tvertices=%u\tlines=%u\tpolygons=%u\tstrips=%u\tattributes=%d", n,
              CellCount(message->GetVertices()), CellCount(message->GetLines()), CellCount(polygons),
              CellCount(message->GetTriangleStrips()), message->GetNumberOfAttributes());
  std::printf("\tpolygon_words=%u", polygons ? polygons->GetTotalSize() / 4 : 0);
  double sum[3] = {0.0, 0.0, 0.0};
  std::string first;
  char buffer[128];
  for (int i = 0; i < n; ++i) {
    igtlFloat32 p[3];
    points->GetPoint(i, p);
    for (int k = 0; k < 3; ++k) sum[k] += p[k];
    if (i < g_first) {
      std::snprintf(buffer, sizeof(buffer), "%s%.9g,%.9g,%.9g", i ? ";" : "", p[0], p[1], p[2]);
      first += buffer;
    }
  }
  std::printf("\tfirst_points=%s\tpoint_sum=%.17g,%.17g,%.17g", first.c_str(), sum[0], sum[1], sum[2]);
  std::string cells;
  for (unsigned int i = 0; i < CellCount(polygons) && i < static_cast<unsigned int>(g_first); ++i) {
    std::list<igtlUint32> cell;
    polygons->GetCell(i, cell);
    if (i) cells += ";";
    bool head = true;
    for (std::list<igtlUint32>::const_iterator it = cell.begin(); it != cell.end(); ++it, head = false) {
      std::snprintf(buffer, sizeof(buffer), "%s%u", head ? "" : ",", *it);
      cells += buffer;
    }
  }
  std::printf("\tfirst_polygons=%s\n", cells.c_str());
  return 0;
}

int String(igtl::Socket* socket, igtl::MessageHeader* header, unsigned int version) {
  igtl::StringMessage::Pointer message = igtl::StringMessage::New();
  if (!ReceiveBody(socket, message, header)) return -1;
  if (int rc = Finish(message, "STRING")) return rc;
  PrintPrefix("STRING", message, version);
  std::printf("\tencoding=%u\ttext=%s\n", message->GetEncoding(), message->GetString());
  return 0;
}

bool AllSeen(const std::map<std::string, Expected>& expected) {
  for (std::map<std::string, Expected>::const_iterator it = expected.begin(); it != expected.end(); ++it)
    if (it->second.seen < it->second.wanted) return false;
  return true;
}

int Missing(const std::map<std::string, Expected>& expected, const char* why) {
  for (std::map<std::string, Expected>::const_iterator it = expected.begin(); it != expected.end(); ++it)
    if (it->second.seen < it->second.wanted)
      std::printf("MISSING\texpected=%s\tseen=%d\twanted=%d\twhy=%s\n", it->first.c_str(), it->second.seen,
                  it->second.wanted, why);
  std::fflush(stdout);
  return 3;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc > 2 && std::strcmp(argv[1], "-p") == 0) {
    g_first = std::atoi(argv[2]);
    argv += 2;
    argc -= 2;
  }
  if (argc < 5) {
    std::fprintf(stderr, "usage: %s [-p K] HOST PORT TIMEOUT_S TYPE:DEVICE[:COUNT]...\n", argv[0]);
    return 1;
  }
  const char* host = argv[1];
  int port = std::atoi(argv[2]);
  double timeout_s = std::atof(argv[3]);
  std::map<std::string, Expected> expected;
  for (int i = 4; i < argc; ++i) {
    std::string spec = argv[i];
    size_t first = spec.find(':');
    size_t last = spec.rfind(':');
    if (first == std::string::npos) {
      std::fprintf(stderr, "expected TYPE:DEVICE[:COUNT], got %s\n", argv[i]);
      return 1;
    }
    Expected e = {1, 0};
    if (last != first) {
      e.wanted = std::atoi(spec.c_str() + last + 1);
      spec = spec.substr(0, last);
    }
    expected[spec] = e;
  }

  typedef std::chrono::steady_clock Clock;
  const Clock::time_point end = Clock::now() + std::chrono::milliseconds(static_cast<long>(timeout_s * 1000));
  igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
  while (socket->ConnectToServer(host, port) != 0) {
    if (Clock::now() > end) {
      std::printf("NO_CONNECTION\t%s:%d\n", host, port);
      return 4;
    }
    igtl::Sleep(20);
  }
  int count = 0;
  while (!AllSeen(expected)) {
    long left_ms = std::chrono::duration_cast<std::chrono::milliseconds>(end - Clock::now()).count();
    if (left_ms <= 0) return Missing(expected, "timeout");
    // The library's Receive returns -1 on a timeout (SO_RCVTIMEO) and 0 when the server hung up;
    // waiting at most until the deadline keeps a quiet stream from hanging the client.
    socket->SetReceiveTimeout(static_cast<int>(left_ms));
    igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
    header->InitPack();
    int got = socket->Receive(header->GetPackPointer(), header->GetPackSize());
    if (got < 0) return Missing(expected, "timeout");
    if (got != header->GetPackSize()) return Missing(expected, "closed");
    unsigned int version = HeaderVersion(header);  // before Unpack(), which byte-swaps the buffer in place
    if (!(header->Unpack() & igtl::MessageHeader::UNPACK_HEADER)) {
      std::printf("BAD_HEADER\n");
      return 2;
    }
    std::string type = header->GetDeviceType();
    std::string device = header->GetDeviceName();
    socket->SetReceiveTimeout(5000);  // ms: a body follows its header at once
    int rc;
    if (type == "TRANSFORM") {
      rc = Transform(socket, header, version);
    } else if (type == "POLYDATA") {
      rc = PolyData(socket, header, version);
    } else if (type == "STRING") {
      rc = String(socket, header, version);
    } else {
      std::printf("MSG\ttype=OTHER\tdevice=%s\tname=%s\n", device.c_str(), type.c_str());
      socket->Skip(header->GetBodySizeToRead(), 1);
      rc = 0;
    }
    if (rc < 0) return Missing(expected, "closed");
    if (rc) return rc;
    ++count;
    std::map<std::string, Expected>::iterator it = expected.find(type + ":" + device);
    if (it != expected.end()) ++it->second.seen;
  }
  std::printf("DONE\tmessages=%d\n", count);
  socket->CloseSocket();
  return 0;
}

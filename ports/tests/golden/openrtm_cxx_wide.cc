// The wide cases of generate_cdr_vectors.py, marshalled as OpenRTM-aist's
// C++ CORBA_CdrSerializer does (rtm/CORBA_CdrMemoryStream.h with omniORB:
// a cdrMemoryStream made after ORB_init, rewindPtrs, setByteSwapFlag with
// the port's byte order, then `data >>= stream`). One difference: the
// stream clears its buffer, so padding is zero rather than whatever was
// in memory; the code sets and the marshalling are the same. Prints
// `case endian hex` lines, endian 0 for big, 1 for little. Built and run by
// generate_cdr_vectors.py against the header rtc_types.hh that omniidl
// writes from the script's IDL.

#include "rtc_types.hh"

#include <cstdio>

namespace {

void emit(const char* name, const cdrMemoryStream& stream, int little) {
  std::printf("%s %d ", name, little);
  const unsigned char* bytes =
      static_cast<const unsigned char*>(stream.bufPtr());
  for (CORBA::ULong i = 0; i < stream.bufSize(); ++i) {
    std::printf("%02x", bytes[i]);
  }
  std::printf("\n");
}

template <class T>
void marshal(const char* name, const T& value) {
  for (int little = 0; little < 2; ++little) {
    cdrMemoryStream stream(CORBA::ULong(0), CORBA::Boolean(1));
    stream.rewindPtrs();
    stream.setByteSwapFlag(little);
    value >>= stream;
    emit(name, stream, little);
  }
}

RTC::Time stamp() {
  RTC::Time tm;
  tm.sec = 0x01020304;
  tm.nsec = 0x0a0b0c0d;
  return tm;
}

void wchar(const char* name, CORBA::WChar c) {
  RTC::TimedWChar value;
  value.tm = stamp();
  value.data = c;
  marshal(name, value);
}

void wstring(const char* name, const CORBA::WChar* s) {
  RTC::TimedWString value;
  value.tm = stamp();
  value.data = s;
  marshal(name, value);
}

}  // namespace

int main(int argc, char** argv) {
  CORBA::ORB_var orb = CORBA::ORB_init(argc, argv);

  wchar("timed_wchar", L'\u03a9');
  wchar("timed_wchar_ascii", L'A');
  wstring("timed_wstring", L"A\u00e9\u20ac");
  wstring("timed_wstring_empty", L"");
  // With a 32-bit wchar_t omniORB refuses a character beyond U+FFFF
  // (BAD_PARAM_WCharOutOfRange); a 16-bit one (Windows) holds it as a
  // surrogate pair, as here.
  wstring("timed_wstring_surrogates", L"x\xd83d\xde00");
  wstring("timed_wstring_feff", L"\ufeffA");

  RTC::TimedWCharSeq chars;
  chars.tm = stamp();
  chars.data.length(3);
  chars.data[0] = L'a';
  chars.data[1] = L'\u03a9';
  chars.data[2] = L'\u20ac';
  marshal("timed_wchar_seq", chars);
  chars.data.length(0);
  marshal("timed_wchar_seq_empty", chars);

  RTC::TimedWStringSeq strings;
  strings.tm = stamp();
  strings.data.length(4);
  strings.data[0] = static_cast<const CORBA::WChar*>(L"a");
  strings.data[1] = static_cast<const CORBA::WChar*>(L"");
  strings.data[2] = static_cast<const CORBA::WChar*>(L"\u03a9\u03bc");
  strings.data[3] = static_cast<const CORBA::WChar*>(L"x\xd83d\xde00");
  marshal("timed_wstring_seq", strings);

  orb->destroy();
  return 0;
}

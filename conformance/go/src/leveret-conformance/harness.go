// Scenario harness for the Go driver (same protocol as python/harness.py):
//
//	conformance-go [--streams|--semantics] --list
//	conformance-go [--streams|--semantics] --url URL --prefix P [--only a,b] [--http URL]
//
// prints {"start": name} then one result record per scenario. --streams
// selects the stream queue scenarios of the `streams` suite, --semantics
// those of the `semantics` suite (which reach the broker's management API
// at --http), instead of the `amqp091-go` suite's.
package main

import (
	"encoding/json"
	"flag"
	"fmt"
	"net/url"
	"os"
	"reflect"
	"runtime/debug"
	"strings"
	"time"
)

type scenarioFn func(t *T)

type entry struct {
	name string
	fn   scenarioFn
}

var registry, streamRegistry, semanticsRegistry []entry

// hang is how long a scenario waits for something it expects: a hang limit,
// generous enough for a loaded CI machine (the wait ends as soon as the
// thing happens).
const hang = 30 * time.Second

func scenario(name string, fn scenarioFn) {
	registry = append(registry, entry{"amqp091-go." + name, fn})
}

// streamScenario registers a scenario of the `streams` suite (streams.go).
func streamScenario(name string, fn scenarioFn) {
	streamRegistry = append(streamRegistry, entry{"streams.amqp091-go." + name, fn})
}

// semanticsScenario registers a scenario of the `semantics` suite
// (semantics.go).
func semanticsScenario(name string, fn scenarioFn) {
	semanticsRegistry = append(semanticsRegistry, entry{"semantics.amqp091-go." + name, fn})
}

type failure struct{ msg string }

type T struct {
	URL, Prefix          string
	HTTP                 string // the management API's base URL (--http), if given
	Host, User, Password string
	Port                 string
	Vhost                string
	obs                  [][]interface{}
	cleanups             []func()
}

func (t *T) N(name string) string { return t.Prefix + name }

func (t *T) URLWith(user, password, vhost string) string {
	if user == "" {
		user = t.User
	}
	if password == "" {
		password = t.Password
	}
	if vhost == "" {
		vhost = t.Vhost
	}
	return fmt.Sprintf("amqp://%s:%s@%s:%s/%s", url.QueryEscape(user), url.QueryEscape(password), t.Host, t.Port, url.QueryEscape(vhost))
}

func (t *T) Obs(label string, v interface{}) { t.obs = append(t.obs, []interface{}{label, plain(v)}) }

func (t *T) Eq(label string, actual, expected interface{}) {
	t.Obs(label, actual)
	a, _ := json.Marshal(plain(actual))
	e, _ := json.Marshal(plain(expected))
	if string(a) != string(e) {
		t.Fatalf("%s: expected %s, got %s", label, e, a)
	}
}

func (t *T) Check(cond bool, format string, args ...interface{}) {
	if !cond {
		t.Fatalf(format, args...)
	}
}

func (t *T) Fatalf(format string, args ...interface{}) {
	panic(failure{fmt.Sprintf(format, args...)})
}

func (t *T) Must(err error, what string) {
	if err != nil {
		t.Fatalf("%s: %v", what, err)
	}
}

func (t *T) Defer(fn func()) { t.cleanups = append(t.cleanups, fn) }

func plain(v interface{}) interface{} {
	switch x := v.(type) {
	case nil:
		return nil
	case []byte:
		return map[string]interface{}{"hex": fmt.Sprintf("%x", x)}
	case time.Time:
		return map[string]interface{}{"timestamp": x.Unix()}
	case error:
		return x.Error()
	}
	rv := reflect.ValueOf(v)
	switch rv.Kind() {
	case reflect.Map:
		out := map[string]interface{}{}
		for _, k := range rv.MapKeys() {
			out[fmt.Sprint(k.Interface())] = plain(rv.MapIndex(k).Interface())
		}
		return out
	case reflect.Slice, reflect.Array:
		out := make([]interface{}, rv.Len())
		for i := range out {
			out[i] = plain(rv.Index(i).Interface())
		}
		return out
	case reflect.Struct:
		return fmt.Sprintf("%+v", v)
	}
	return v
}

func waitUntil(t *T, timeout time.Duration, what string, pred func() bool) {
	deadline := time.Now().Add(timeout)
	for time.Now().Before(deadline) {
		if pred() {
			return
		}
		time.Sleep(20 * time.Millisecond)
	}
	t.Fatalf("timed out after %v waiting for %s", timeout, what)
}

func replyName(text string) string { return strings.TrimSpace(strings.SplitN(text, " - ", 2)[0]) }

func main() {
	list := flag.Bool("list", false, "list scenarios")
	u := flag.String("url", "", "broker URL")
	prefix := flag.String("prefix", "cf-", "name prefix")
	only := flag.String("only", "", "comma-separated scenario names")
	streams := flag.Bool("streams", false, "the stream queue scenarios (the streams suite)")
	semantics := flag.Bool("semantics", false, "the semantics suite's scenarios")
	httpURL := flag.String("http", "", "the broker's management API, e.g. http://127.0.0.1:15672")
	flag.Parse()
	if *streams {
		registry = streamRegistry
	}
	if *semantics {
		registry = semanticsRegistry
	}
	if *list {
		for _, e := range registry {
			fmt.Println(e.name)
		}
		return
	}
	want := map[string]bool{}
	for _, n := range strings.Split(*only, ",") {
		if n != "" {
			want[n] = true
		}
	}
	pu, err := url.Parse(*u)
	if err != nil {
		fmt.Fprintln(os.Stderr, err)
		os.Exit(2)
	}
	pw, _ := pu.User.Password()
	vhost := strings.TrimPrefix(pu.Path, "/")
	if vhost == "" {
		vhost = "/"
	} else if v, err := url.PathUnescape(vhost); err == nil {
		vhost = v
	}
	port := pu.Port()
	if port == "" {
		port = "5672"
	}
	enc := json.NewEncoder(os.Stdout)
	for _, e := range registry {
		if len(want) > 0 && !want[e.name] {
			continue
		}
		enc.Encode(map[string]string{"start": e.name})
		t := &T{URL: *u, HTTP: *httpURL, Prefix: *prefix, Host: pu.Hostname(), Port: port, User: pu.User.Username(), Password: pw, Vhost: vhost, obs: [][]interface{}{}}
		start := time.Now()
		done := make(chan string, 1)
		go func() {
			msg := ""
			defer func() {
				if r := recover(); r != nil {
					if f, ok := r.(failure); ok {
						msg = f.msg
					} else {
						msg = fmt.Sprintf("panic: %v\n%s", r, debug.Stack())
					}
				}
				for i := len(t.cleanups) - 1; i >= 0; i-- {
					func() { defer func() { recover() }(); t.cleanups[i]() }()
				}
				done <- msg
			}()
			e.fn(t)
		}()
		var msg string
		select {
		case msg = <-done:
		case <-time.After(60 * time.Second):
			msg = "scenario timed out after 60s"
		}
		rec := map[string]interface{}{"name": e.name, "ok": msg == "", "error": nil, "obs": t.obs, "ms": time.Since(start).Milliseconds()}
		if msg != "" {
			rec["error"] = msg
		}
		enc.Encode(rec)
	}
}

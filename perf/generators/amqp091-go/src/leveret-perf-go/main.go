// leveret-perf-go: an AMQP 0.9.1 throughput load generator on the standard RabbitMQ Go client
// (github.com/rabbitmq/amqp091-go), independent of Leveret's own code. Its flags and its JSON
// summary mirror lavinmqperf's `throughput` subcommand. See perf/generators/README.md.
package main

import (
	"context"
	"crypto/rand"
	"encoding/hex"
	"flag"
	"fmt"
	"math"
	"os"
	"strconv"
	"strings"
	"sync"
	"sync/atomic"
	"time"

	amqp "github.com/rabbitmq/amqp091-go"
)

type options struct {
	uri        string
	publishers int
	consumers  int
	size       int
	seconds    int
	ack        int
	prefetch   int
	persistent bool
	confirm    int
	quiet      bool
	json       bool
	rate       int
	queue      string
}

var (
	opt       options
	published atomic.Int64 // publishes (confirmed ones when -c)
	consumed  atomic.Int64 // deliveries received
	nacked    atomic.Int64 // publishes the broker nacked (-c only)
	stopping  atomic.Bool  // set when the run ends: errors after it are the shutdown's own
	failures  = make(chan string, 1)
)

// fail reports an error that ends the run (the first one wins).
func fail(format string, args ...interface{}) {
	select {
	case failures <- fmt.Sprintf(format, args...):
	default:
	}
}

func die(format string, args ...interface{}) {
	fmt.Fprintf(os.Stderr, "leveret-perf-go: "+format+"\n", args...)
	os.Exit(1)
}

func parseFlags() {
	fs := flag.NewFlagSet("leveret-perf-go", flag.ContinueOnError)
	fs.Usage = func() {
		fmt.Fprint(os.Stderr, `usage: leveret-perf-go [throughput] [flags]   (the flags of lavinmqperf throughput)
  --uri URI             broker (default amqp://guest:guest@127.0.0.1:5672/%2f)
  -x, --publishers N    publishers, one connection each (default 1)
  -y, --consumers N     consumers, one connection each (default 1)
  -s, --size BYTES      message body size (default 16)
  -z, --time SECONDS    duration (default 10)
  -a, --ack N           ack every N messages, multiple=true (default 0: no-ack consumers)
  -P, --prefetch N      consumer prefetch (default 0: unlimited)
  -p, --persistent      delivery mode 2 and a durable queue
  -c, --confirm N       publisher confirms, at most N unconfirmed per publisher (default 0: off)
  -r, --rate N          max msgs/s per publisher (default 0: unlimited)
  -u, --queue NAME      queue (default: a fresh perf-go-<random>, deleted at the end)
  -q, --quiet           no per-second rates on stderr
  -j, --json            accepted; the JSON summary is always the last line of stdout
`)
	}
	str := func(p *string, def, usage string, names ...string) {
		for _, n := range names {
			fs.StringVar(p, n, def, usage)
		}
	}
	num := func(p *int, def int, usage string, names ...string) {
		for _, n := range names {
			fs.IntVar(p, n, def, usage)
		}
	}
	boolean := func(p *bool, usage string, names ...string) {
		for _, n := range names {
			fs.BoolVar(p, n, false, usage)
		}
	}
	str(&opt.uri, "amqp://guest:guest@127.0.0.1:5672/%2f", "broker URI", "uri")
	num(&opt.publishers, 1, "publishers, one connection each", "x", "publishers")
	num(&opt.consumers, 1, "consumers, one connection each", "y", "consumers")
	num(&opt.size, 16, "message body size in bytes", "s", "size")
	num(&opt.seconds, 10, "run for this many seconds", "z", "time")
	num(&opt.ack, 0, "ack every N messages with multiple=true (0: no-ack consumers)", "a", "ack")
	num(&opt.prefetch, 0, "consumer prefetch count (0: unlimited)", "P", "prefetch")
	boolean(&opt.persistent, "persistent messages (delivery mode 2) and a durable queue", "p", "persistent")
	num(&opt.confirm, 0, "publisher confirms, at most N unconfirmed per publisher (0: off)", "c", "confirm")
	boolean(&opt.quiet, "no per-second rates on stderr", "q", "quiet")
	boolean(&opt.json, "accepted for lavinmqperf compatibility: the JSON summary is always printed", "j", "json")
	num(&opt.rate, 0, "max publish rate per publisher, msgs/s (0: unlimited)", "r", "rate")
	str(&opt.queue, "", "queue name (default: a fresh perf-go-<random>, deleted at the end)", "queue", "u")

	args := os.Args[1:]
	if len(args) > 0 && args[0] == "throughput" {
		args = args[1:]
	}
	if err := fs.Parse(args); err != nil {
		if err == flag.ErrHelp {
			os.Exit(0)
		}
		os.Exit(2)
	}
	switch {
	case fs.NArg() > 0:
		die("unexpected argument %q", fs.Arg(0))
	case opt.publishers < 0 || opt.consumers < 0 || opt.publishers+opt.consumers == 0:
		die("-x and -y must be >= 0 and not both 0")
	case opt.size < 0:
		die("-s must be >= 0")
	case opt.seconds <= 0:
		die("-z must be > 0")
	case opt.ack < 0 || opt.confirm < 0 || opt.rate < 0:
		die("-a, -c and -r must be >= 0")
	case opt.prefetch < 0 || opt.prefetch > math.MaxUint16:
		die("-P must be between 0 and 65535")
	}
}

// watch turns a connection's or channel's closing with an error during the run into a failure.
func watch(who string, conn *amqp.Connection, ch *amqp.Channel) {
	connClosed := conn.NotifyClose(make(chan *amqp.Error, 1))
	chClosed := ch.NotifyClose(make(chan *amqp.Error, 1))
	go func() {
		var err *amqp.Error
		select {
		case err = <-connClosed:
		case err = <-chClosed:
		}
		if err != nil && !stopping.Load() {
			fail("%s: closed by the broker or the network: %v", who, err)
		}
	}()
}

func open(who string) (*amqp.Connection, *amqp.Channel, error) {
	conn, err := amqp.Dial(opt.uri)
	if err != nil {
		return nil, nil, fmt.Errorf("%s: cannot connect to %s: %v", who, opt.uri, err)
	}
	ch, err := conn.Channel()
	if err != nil {
		conn.Close()
		return nil, nil, fmt.Errorf("%s: cannot open a channel: %v", who, err)
	}
	return conn, ch, nil
}

type publisher struct {
	name     string
	conn     *amqp.Connection
	ch       *amqp.Channel
	confirms chan amqp.Confirmation
	blocked  atomic.Bool
}

func newPublisher(i int) (*publisher, error) {
	p := &publisher{name: fmt.Sprintf("publisher %d", i+1)}
	var err error
	if p.conn, p.ch, err = open(p.name); err != nil {
		return nil, err
	}
	if opt.confirm > 0 {
		if err := p.ch.Confirm(false); err != nil {
			p.conn.Close()
			return nil, fmt.Errorf("%s: confirm.select: %v", p.name, err)
		}
		// At most opt.confirm are outstanding, so the library never waits to hand one over.
		p.confirms = p.ch.NotifyPublish(make(chan amqp.Confirmation, opt.confirm))
	}
	blockings := p.conn.NotifyBlocked(make(chan amqp.Blocking, 4))
	go func() {
		for b := range blockings {
			p.blocked.Store(b.Active)
			if b.Active {
				fmt.Fprintf(os.Stderr, "%s: connection.blocked (%s): waiting\n", p.name, b.Reason)
			} else {
				fmt.Fprintf(os.Stderr, "%s: connection.unblocked\n", p.name)
			}
		}
	}()
	watch(p.name, p.conn, p.ch)
	return p, nil
}

// settle counts one confirmation; false when the channel has closed.
func settle(c amqp.Confirmation, ok bool) bool {
	if !ok {
		return false
	}
	if c.Ack {
		published.Add(1)
	} else {
		nacked.Add(1)
	}
	return true
}

func (p *publisher) run(start <-chan struct{}, stop <-chan struct{}) {
	body := make([]byte, opt.size)
	for i := range body {
		body[i] = byte(i%27 + 64)
	}
	msg := amqp.Publishing{Body: body}
	if opt.persistent {
		msg.DeliveryMode = amqp.Persistent
	}
	ctx := context.Background()
	<-start
	outstanding := 0
	second, inSecond := time.Now(), 0
	for !stopping.Load() {
		for p.blocked.Load() && !stopping.Load() {
			time.Sleep(10 * time.Millisecond)
		}
		if opt.confirm > 0 {
			// Take the confirmations already in, and wait for one if opt.confirm are outstanding.
		drain:
			for outstanding > 0 {
				if outstanding < opt.confirm {
					select {
					case c, ok := <-p.confirms:
						if !settle(c, ok) {
							return
						}
						outstanding--
					default:
						break drain
					}
				} else {
					select {
					case c, ok := <-p.confirms:
						if !settle(c, ok) {
							return
						}
						outstanding--
					case <-stop:
						return
					}
				}
			}
		}
		if err := p.ch.PublishWithContext(ctx, "", opt.queue, false, false, msg); err != nil {
			if !stopping.Load() {
				fail("%s: publish: %v", p.name, err)
			}
			return
		}
		if opt.confirm > 0 {
			outstanding++
		} else {
			published.Add(1)
		}
		if opt.rate > 0 {
			inSecond++
			if inSecond >= opt.rate {
				if wait := time.Until(second.Add(time.Second)); wait > 0 {
					select {
					case <-time.After(wait):
					case <-stop:
						return
					}
				}
				second, inSecond = time.Now(), 0
			}
		}
	}
}

type consumer struct {
	name       string
	conn       *amqp.Connection
	ch         *amqp.Channel
	deliveries <-chan amqp.Delivery
}

func newConsumer(i int) (*consumer, error) {
	c := &consumer{name: fmt.Sprintf("consumer %d", i+1)}
	var err error
	if c.conn, c.ch, err = open(c.name); err != nil {
		return nil, err
	}
	if opt.prefetch > 0 {
		if err := c.ch.Qos(opt.prefetch, 0, false); err != nil {
			c.conn.Close()
			return nil, fmt.Errorf("%s: basic.qos: %v", c.name, err)
		}
	}
	watch(c.name, c.conn, c.ch)
	c.deliveries, err = c.ch.Consume(opt.queue, "", opt.ack == 0, false, false, false, nil)
	if err != nil {
		c.conn.Close()
		return nil, fmt.Errorf("%s: basic.consume: %v", c.name, err)
	}
	return c, nil
}

func (c *consumer) run() {
	n := 0
	for d := range c.deliveries {
		consumed.Add(1)
		if opt.ack > 0 {
			n++
			if n%opt.ack == 0 {
				if err := d.Ack(true); err != nil {
					if !stopping.Load() {
						fail("%s: basic.ack: %v", c.name, err)
					}
					return
				}
			}
		}
	}
	time.Sleep(100 * time.Millisecond) // a channel or connection error, if that is the cause, reports first
	if !stopping.Load() {
		fail("%s: the broker ended the consumer (basic.cancel or channel closed)", c.name)
	}
}

// within runs f, giving up on waiting for it after d (f keeps running: the process is about to exit).
func within(d time.Duration, f func()) bool {
	done := make(chan struct{})
	go func() { f(); close(done) }()
	select {
	case <-done:
		return true
	case <-time.After(d):
		return false
	}
}

func randomName() string {
	b := make([]byte, 6)
	if _, err := rand.Read(b); err != nil {
		die("random queue name: %v", err)
	}
	return "perf-go-" + hex.EncodeToString(b)
}

func main() {
	parseFlags()
	ownQueue := opt.queue == ""
	if ownQueue {
		opt.queue = randomName()
	}

	// The queue is declared once, up front, on a connection of its own that also deletes it.
	adminConn, admin, err := open("setup")
	if err != nil {
		die("%v", err)
	}
	if _, err := admin.QueueDeclare(opt.queue, opt.persistent, false, false, false, nil); err != nil {
		die("setup: queue.declare %s: %v", opt.queue, err)
	}

	// Connect everybody (concurrently), then start the clock.
	pubs := make([]*publisher, opt.publishers)
	cons := make([]*consumer, opt.consumers)
	var wg sync.WaitGroup
	setupErrs := make(chan error, opt.publishers+opt.consumers)
	for i := range pubs {
		wg.Add(1)
		go func(i int) {
			defer wg.Done()
			p, err := newPublisher(i)
			if err != nil {
				setupErrs <- err
			}
			pubs[i] = p
		}(i)
	}
	for i := range cons {
		wg.Add(1)
		go func(i int) {
			defer wg.Done()
			c, err := newConsumer(i)
			if err != nil {
				setupErrs <- err
			}
			cons[i] = c
		}(i)
	}
	wg.Wait()
	select {
	case err := <-setupErrs:
		die("%v", err)
	default:
	}

	start, stop := make(chan struct{}), make(chan struct{})
	var pubsDone sync.WaitGroup
	for _, p := range pubs {
		pubsDone.Add(1)
		go func(p *publisher) { defer pubsDone.Done(); p.run(start, stop) }(p)
	}
	for _, c := range cons {
		go c.run()
	}
	began := time.Now()
	close(start)

	deadline := time.NewTimer(time.Duration(opt.seconds) * time.Second)
	tick := time.NewTicker(time.Second)
	lastPub, lastCons := int64(0), int64(0)
run:
	for {
		select {
		case msg := <-failures:
			die("%s", msg)
		case <-tick.C:
			if !opt.quiet {
				p, c := published.Load(), consumed.Load()
				fmt.Fprintf(os.Stderr, "Publish rate: %d msgs/s Consume rate: %d msgs/s\n", p-lastPub, c-lastCons)
				lastPub, lastCons = p, c
			}
		case <-deadline.C:
			break run
		}
	}
	stopping.Store(true)
	elapsed := time.Since(began).Seconds()
	pubCount, consCount := published.Load(), consumed.Load()
	select { // a failure just before the deadline still fails the run
	case msg := <-failures:
		die("%s", msg)
	default:
	}
	close(stop)
	tick.Stop()

	// Stop the publishers, then close every connection and delete our queue. Each step has a time
	// limit: a publisher can be stuck writing to a broker that has stopped reading.
	if !within(5*time.Second, pubsDone.Wait) {
		fmt.Fprintln(os.Stderr, "leveret-perf-go: publishers still busy 5 s after the end (flow control?); closing anyway")
	}
	within(5*time.Second, func() {
		var closing sync.WaitGroup
		for _, p := range pubs {
			closing.Add(1)
			go func(p *publisher) { defer closing.Done(); p.conn.Close() }(p)
		}
		for _, c := range cons {
			closing.Add(1)
			go func(c *consumer) { defer closing.Done(); c.conn.Close() }(c)
		}
		closing.Wait()
	})
	if ownQueue {
		var derr error
		if !within(10*time.Second, func() { _, derr = admin.QueueDelete(opt.queue, false, false, false) }) {
			derr = fmt.Errorf("no reply in 10 s")
		}
		if derr != nil {
			fmt.Fprintf(os.Stderr, "leveret-perf-go: warning: queue.delete %s: %v\n", opt.queue, derr)
		}
	}
	within(5*time.Second, func() { adminConn.Close() })
	if n := nacked.Load(); n > 0 {
		fmt.Fprintf(os.Stderr, "leveret-perf-go: warning: the broker nacked %d publishes (not counted)\n", n)
	}

	secs := strconv.FormatFloat(elapsed, 'f', -1, 64)
	if !strings.ContainsAny(secs, ".e") {
		secs += ".0"
	}
	fmt.Printf("{\"elapsed_seconds\":%s,\"avg_pub_rate\":%d,\"avg_consume_rate\":%d}\n",
		secs, int64(math.Round(float64(pubCount)/elapsed)), int64(math.Round(float64(consCount)/elapsed)))
}
